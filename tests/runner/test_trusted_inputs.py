"""Inputs checked by what they are before work, and every reader as strict as ``results``: each case
once scored or read silently, fed to ``cli.main`` (notebooks in this process) with four small photographs."""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import cv2
import numpy as np
import pandas as pd
import pytest
import yaml
from helpers import (
    FLIPPED,
    PAIRS,
    assert_nothing_written,
    in_process_notebooks,
    one_sentence,
    params_file,
    run_cli,
    snapshot,
)

from gvbench_nb import notebook, run_and_publish
from gvbench_nb.data.sequences import Pair, Sequence, write_pairs
from gvbench_nb.reporting import report
from gvbench_nb.runner import config, input_checks, method_outputs, runs, sequence_build

pytestmark = pytest.mark.reliability


@pytest.fixture
def notebooks_here(monkeypatch):
    monkeypatch.setattr(run_and_publish, "execute_notebook", in_process_notebooks)


# ------------------------------------------------------- images by content --
@pytest.mark.parametrize("how", ["copy", "symlink"])
def test_two_images_of_one_content_are_a_self_pair_refused_with_file_and_line(
    tmp_path, root, capsys, notebooks_here, how
):
    same = root / "reference" / "same.png"
    if how == "copy":
        shutil.copyfile(root / "query" / "a.png", same)
    else:
        same.symlink_to(root / "query" / "a.png")
    path = params_file(tmp_path, pairs=[*PAIRS, Pair("query/a.png", "reference/same.png", 1)])
    code, _, err = run_cli(capsys, "run", str(path))
    assert code == 2
    assert f"{tmp_path / 'params-pairs.txt'}:5: self-pair by content" in one_sentence(err)
    assert "query/a.png and reference/same.png hold the same bytes" in err
    assert_nothing_written(tmp_path)


@pytest.mark.real_data
def test_two_queries_of_one_content_each_with_its_own_reference_are_scored(shared_data, tmp_path):
    # Gardens Point's night_right frames 179 and 183 are byte-identical: two queries, not a self-pair.
    root = shared_data / "gardens_point"
    assert (root / "night_right/Image179.jpg").read_bytes() == (root / "night_right/Image183.jpg").read_bytes()
    pairs = [Pair("night_right/Image179.jpg", "day_right/Image181.jpg", 1)]
    pairs.append(Pair("night_right/Image183.jpg", "day_right/Image181.jpg", 1))
    assert input_checks.check_image_contents(Sequence("gp", root, pairs), tmp_path, False) == {}


# ---------------------------------------------------------- damaged images --
def damaged_jpeg(root: Path) -> Path:
    """``reference/c.jpg``: a JPEG of a photo with 200 bytes of its entropy-coded data zeroed."""
    data = bytearray(cv2.imencode(".jpg", cv2.imread(str(root / "reference" / "b.png")))[1].tobytes())
    middle = len(data) // 2
    data[middle : middle + 200] = bytes(200)
    path = root / "reference" / "c.jpg"
    path.write_bytes(bytes(data))
    assert cv2.imdecode(np.frombuffer(bytes(data), np.uint8), cv2.IMREAD_COLOR) is not None  # decodes, warning
    return path


def test_a_damaged_jpeg_is_named_and_refused_before_work_unless_allowed(tmp_path, root, capsys, notebooks_here):
    jpeg = damaged_jpeg(root)
    pairs = [*PAIRS, Pair("query/b.png", "reference/c.jpg", 1)]
    code, _, err = run_cli(capsys, "run", str(params_file(tmp_path, pairs=pairs)))
    assert code == 2
    assert_nothing_written(tmp_path)
    assert f"first {jpeg} (pair 4: query/b.png reference/c.jpg)" in one_sentence(err)
    assert "Corrupt JPEG data" in err and "allow_damaged_images: true" in err  # libjpeg's words, from its stderr
    # Allowed explicitly: scored, and listed in the run's manifest.
    code, _, err = run_cli(capsys, "run", str(params_file(tmp_path, pairs=pairs, allow_damaged_images=True)))
    assert code == 0, err
    (_, manifest), *_ = runs.finished_runs(tmp_path / "out")
    damaged = manifest["damaged_images"]
    assert list(damaged) == ["reference/c.jpg"] and "Corrupt JPEG data" in damaged["reference/c.jpg"]
    checked = json.loads((tmp_path / "cache" / "decoder-checks.json").read_text())
    assert len(checked) == 5 and sum(bool(said) for said in checked.values()) == 1  # each content decoded once


def test_an_image_that_does_not_decode_is_refused_before_work_even_when_damage_is_allowed(
    tmp_path, root, capsys, notebooks_here
):
    (root / "reference" / "b.png").write_bytes((root / "reference" / "b.png").read_bytes()[:2000])
    code, _, err = run_cli(capsys, "run", str(params_file(tmp_path, allow_damaged_images=True)))
    assert code == 2
    assert_nothing_written(tmp_path)
    assert f"cannot decode image {root / 'reference' / 'b.png'}" in one_sentence(err)


# ------------------------------------------------------ keys given twice --
@pytest.mark.parametrize(
    "text, key, line, first",
    [
        ("verifier: {threshold_px: 3, threshold_px: 1}\n", "threshold_px", 2, "the same line"),
        ("builder_options: {a: {b: 1, b: 2}}\n", "b", 2, "the same line"),
        ("verifier:\n  {threshold_px: 3,\n   threshold_px: 1}\n", "threshold_px", 4, "line 3"),
        ("methods: [orb-nn]\nmethods: [sift-nn]\n", "methods", 3, "line 2"),
        ("verifier:\n  threshold_px: 1.0\n  threshold_px: 2.0\n", "threshold_px", 4, "line 3"),
    ],
    ids=["flow", "flow-nested", "flow-two-lines", "block", "block-nested"],
)
def test_a_key_given_twice_in_any_yaml_style_is_refused_naming_file_and_line(tmp_path, root, text, key, line, first):
    path = params_file(tmp_path)
    body = path.read_text()
    path.write_text(body.split("\n", 1)[0] + "\n" + text + body.split("\n", 1)[1])
    with pytest.raises(config.ParamsError, match=rf"^{path}:{line}: key '{key}' is given twice \(first on {first}\)"):
        config.load_params(path)


# ------------------------------------------------------- every recipe a row --
@pytest.mark.parametrize(
    "changes", [{"verifier": {"threshold_px": 0.25, "max_iters": 5}}, {"seed": 1}], ids=["verifier", "seed"]
)
def test_a_method_added_under_another_verifier_or_seed_shows_beside_the_earlier_one(
    tmp_path, root, capsys, notebooks_here, changes
):
    out = tmp_path / "out"
    assert run_cli(capsys, "run", str(params_file(tmp_path)))[0] == 0
    (first, _), *_ = runs.finished_runs(out)
    before = snapshot(first)
    added = params_file(tmp_path, "added.yaml", methods=["sift-opencv-nn"], **changes)
    code, _, err = run_cli(capsys, "run", str(added))
    assert code == 0, err
    assert snapshot(first) == before and len(runs.finished_runs(out)) == 2
    assert list(pd.read_csv(out / "results.csv")["method"]) == ["orb-nn", "sift-opencv-nn"]  # a row a recipe
    assert "not in this table" not in err


# ------------------------------------------- every reader as strict as results --
def edit_a_runs_labels(tmp_path: Path) -> None:
    table = method_outputs.method_dir(tmp_path / "out", "orb-nn") / "pairs.csv"
    frame = pd.read_csv(table)
    frame.loc[1, "label"] = 1 - frame.loc[1, "label"]
    frame.to_csv(table, index=False)


def make_earlier_layout(tmp_path: Path) -> None:
    shutil.rmtree(tmp_path / "out" / runs.RUNS)
    (tmp_path / "out" / runs.OLD_RECORD).write_text("{}")


EDITS = {
    "labels": lambda tmp_path: write_pairs(tmp_path / "params-pairs.txt", [PAIRS[0], FLIPPED[1], *PAIRS[2:]]),
    "labels-of-one-table": edit_a_runs_labels,
    "earlier-layout": make_earlier_layout,
}


@pytest.fixture
def started(monkeypatch) -> list[str]:
    """Readers' work, stubbed to say it started: the report's notebooks, JupyterLab."""
    work: list[str] = []
    monkeypatch.setattr(report, "write_report", lambda *a: work.append("report") or (Path("index.html"), []))
    monkeypatch.setattr(os, "execv", lambda *a: work.append("explore"))
    return work


@pytest.mark.parametrize("edit", list(EDITS.values()), ids=list(EDITS))
def test_every_reader_refuses_what_results_refuses_before_any_work_or_file(
    tmp_path, root, capsys, notebooks_here, started, edit
):
    path = params_file(tmp_path, methods=["orb-nn", "sift-opencv-nn"])
    assert run_cli(capsys, "run", str(path))[0] == 0
    out = tmp_path / "out"
    edit(tmp_path)
    code, printed, refused = run_cli(capsys, "results", str(out))
    assert code == 2 and printed == "" and one_sentence(refused)
    before = snapshot(out)
    readers = {
        "compare": ["compare", str(out)],
        "report": ["report", "--outputs-root", str(tmp_path), "--output-dir", str(tmp_path / "report")],
        "explore": ["explore", str(out), "--no-browser"],
    }
    for reader, argv in readers.items():
        code, _, err = run_cli(capsys, *argv)
        assert (reader, code, err) == (reader, 2, refused)
    with pytest.raises(Exception) as error:
        notebook.load_results(out, tmp_path / "figures")
    assert f"error: {error.value}\n" == refused
    assert started == [] and snapshot(out) == before
    assert not (tmp_path / "report").exists() and not (tmp_path / "figures").exists()


# ------------------------------------------------- typed paths are not built into --
def test_an_image_root_typed_on_the_command_line_is_never_rendered_into(tmp_path, capsys, monkeypatch):
    builder_calls: list[str] = []

    def render(params: dict) -> None:  # the sample builder, stubbed: the run stops (exit 130), nothing rendered
        builder_calls.append(params["image_root"])
        raise KeyboardInterrupt

    monkeypatch.setitem(sequence_build.PAIR_BUILDERS, "sample", render)
    params = {"sequence": "sample", "pairs_builder": "sample", "image_root": "data/sample", "output_dir": "out"}
    params.update(pairs="data/sample/pairs.txt", methods=["orb-nn"], profile="repository")
    path = tmp_path / "sample.yaml"
    path.write_text(yaml.safe_dump(params))
    typo = tmp_path / "dta" / "sample"
    code, _, err = run_cli(capsys, "run", str(path), "--image-root", str(typo))
    assert code == 2 and f"--image-root {typo} does not exist" in one_sentence(err)
    assert builder_calls == [] and not typo.parent.exists() and not (tmp_path / "out").exists()
    typo.mkdir(parents=True)
    code, _, err = run_cli(capsys, "run", str(path), "--image-root", str(typo))
    assert code == 2 and f"--image-root {typo} holds no rendered route" in one_sentence(err)
    # The params file's own image_root is rendered (what `make demo` does on a fresh clone) ...
    assert run_cli(capsys, "run", str(path))[0] == 130
    assert builder_calls == [str(tmp_path / "data" / "sample")]
    # ... and a typed folder holding a rendered route is used as it is.
    (typo / "generator.json").write_text("{}")
    assert run_cli(capsys, "run", str(path), "--image-root", str(typo))[0] == 130
    assert builder_calls[-1] == str(typo)


# ------------------------------------------------------ environment variables --
@pytest.mark.parametrize(
    "name, value",
    [
        ("GVBENCH_THREADS", "abc"),
        ("GVBENCH_THREADS", "-1"),
        ("GVBENCH_MAX_PIXELS", "abc"),
        ("GVBENCH_DATA", "file"),
        ("GVBENCH_CACHE", "file"),
    ],
)
def test_a_bad_environment_variable_is_one_sentence_naming_it_before_any_folder(
    tmp_path, root, capsys, notebooks_here, monkeypatch, name, value
):
    if value == "file":
        value = str(tmp_path / "a-file")
        Path(value).write_text("")
    monkeypatch.setenv(name, value)
    code, _, err = run_cli(capsys, "run", str(params_file(tmp_path)))
    assert code == 2 and name in one_sentence(err) and repr(value) in err
    assert_nothing_written(tmp_path)


@pytest.mark.parametrize(
    "option",
    [["--shard", "5/2"], ["--shard", "x"], ["--dask", "--shards", "0"], ["--output-dir", ""], ["--image-root", " "]],
)
def test_a_bad_run_option_is_one_sentence_naming_it_before_any_folder(tmp_path, root, capsys, option):
    code, _, err = run_cli(capsys, "run", str(params_file(tmp_path)), *option)
    assert code == 2 and option[-2] in one_sentence(err)
    assert_nothing_written(tmp_path)
