"""A sequence or method name names the output's files: one that is not a plain file-name component
is refused in one sentence, before any folder, at every door a user gives it through."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest
import yaml
from helpers import PAIRS, write_params, write_root

from gvbench_nb import notebook
from gvbench_nb.data.sequences import write_pairs
from gvbench_nb.runner import config


def every_path(folder: Path) -> set[str]:
    """Every file and folder under ``folder`` (what a refused command must leave as it was)."""
    return {str(p.relative_to(folder)) for p in folder.rglob("*")}


def refused(cwd: Path, *argv: str) -> str:
    """``python -m gvbench_nb ARGV`` in ``cwd``, expected to exit 2 with one line on stderr; that line."""
    done = subprocess.run(
        [sys.executable, "-m", "gvbench_nb", *argv],
        capture_output=True,
        text=True,
        timeout=600,
        cwd=cwd,
        env={**os.environ, "PYTHONPATH": str(config.PROJECT_ROOT)},
    )
    lines = done.stderr.strip().splitlines()
    assert done.returncode == 2 and len(lines) == 1 and "Traceback" not in done.stderr, done.stderr[-3000:]
    return lines[0]


def study(folder: Path, **changes: object) -> Path:
    """A params file of the four photographs' sequence, deep enough in ``folder`` that ``../..`` stays in it."""
    work = folder / "a" / "b" / "c"
    work.mkdir(parents=True)
    write_root(work / "images")
    write_pairs(work / "pairs.txt", PAIRS)
    return write_params(work, methods=["orb-nn"], **changes)


@pytest.mark.reliability
@pytest.mark.parametrize("command", [["run"], ["build"], ["data", "check"]], ids=" ".join)
@pytest.mark.parametrize("name", ["../../x", "a/b"])
def test_a_params_sequence_that_is_not_a_plain_name_is_refused_before_any_folder(tmp_path, command, name):
    params = study(tmp_path, sequence=name)
    before = every_path(tmp_path)
    said = refused(params.parent, *command, str(params))
    assert said.startswith(f"error: {params}: sequence {name!r} holds a path separator"), said
    assert "give a plain name such as" in said
    assert every_path(tmp_path) == before


@pytest.mark.reliability
@pytest.mark.parametrize(
    ("option", "sequence", "method"),
    [("--sequence", "../../keep", "m"), ("--method", "s", "../m"), ("--method", "s", "..")],
)
def test_an_imported_sequence_or_method_that_is_not_a_plain_name_is_refused_before_any_folder(
    tmp_path, option, sequence, method
):
    work = tmp_path / "a" / "b" / "c"
    work.mkdir(parents=True)
    keep = tmp_path / "a" / "keep_ext.npy"
    keep.write_bytes(b"the user's own")
    scores = work / "scores.csv"
    rows = [f"{p.query},{p.reference},{p.label},{score}\n" for p, score in zip(PAIRS, (90, 10, 80, 20))]
    scores.write_text("query,reference,label,score\n" + "".join(rows))
    before = every_path(tmp_path)
    argv = ["import-scores", str(scores), "--sequence", sequence, "--method", method, "--output-dir", "OUT"]
    said = refused(work, *argv)
    name = {"--sequence": sequence, "--method": method}[option]
    assert f"{option} {name!r} " in said and "give a plain name such as" in said, said
    assert every_path(tmp_path) == before and keep.read_bytes() == b"the user's own"


@pytest.mark.reliability
@pytest.mark.parametrize("name", ["../../x", "a/b", "..", "a\nb"])
def test_a_notebook_sequence_that_is_not_a_plain_name_is_refused_before_any_folder(tmp_path, monkeypatch, name):
    keys = config.read_yaml_mapping(study(tmp_path))
    monkeypatch.chdir(tmp_path)
    before = every_path(tmp_path)
    given = [
        ("the notebook's parameters", None, {"sequence": name}),  # papermill -p sequence NAME
        ("the notebook's parameters", None, {**keys, "sequence": name}),  # papermill -f P.yaml -p sequence NAME
    ]
    for source, params_file, keys_given in given:
        with pytest.raises(config.ParamsError) as error:
            notebook.load_sequence(params_file, **keys_given)
        said = str(error.value)
        assert said.startswith(f"{source}: sequence {name!r} ") and "give a plain name such as" in said, said
        assert len(said.splitlines()) == 1
    written = tmp_path / "a" / "b" / "c" / "params.yaml"
    written.write_text(yaml.safe_dump({**keys, "sequence": name}))  # papermill -p params_file P.yaml
    with pytest.raises(config.ParamsError, match=f"^{re.escape(str(written))}: sequence "):
        notebook.load_sequence(str(written))
    assert every_path(tmp_path) == before


@pytest.mark.reliability
def test_a_folder_recorded_under_a_name_that_is_not_plain_is_refused_before_any_figure(tmp_path, monkeypatch):
    from gvbench_nb.runner import method_outputs, score_files

    work = tmp_path / "a" / "b" / "c"
    work.mkdir(parents=True)
    scores = work / "scores.csv"
    rows = [f"{p.query},{p.reference},{p.label},{score}\n" for p, score in zip(PAIRS, (90, 10, 80, 20))]
    scores.write_text("query,reference,label,score\n" + "".join(rows))
    # A folder some other tool (or an older version) recorded under the sequence '../../x'.
    with monkeypatch.context() as patch:
        patch.setattr(score_files, "check_name", lambda name, option: name, raising=False)
        score_files.import_scores(scores, "../../x", "m", work / "out")
    before = every_path(tmp_path)
    with pytest.raises(method_outputs.ResultsError) as error:
        notebook.load_results([work / "out"], work / "figures")
    assert "its sequence '../../x' holds a path separator, so it cannot name figures" in str(error.value)
    said = refused(work, "report", str(work / "out"), "--output-dir", str(work / "report"))
    assert "its sequence '../../x' holds a path separator" in said
    said = refused(work, "results", str(work / "out"), "--export", "npy")  # out/m/../../x_m_ID.npy
    assert "its sequence '../../x' holds a path separator, so it cannot name the export" in said
    assert every_path(tmp_path) == before
