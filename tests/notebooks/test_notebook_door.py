"""A notebook's run says what made it: the params file papermill was given (path and SHA-256) and the
notebook; every record names the params by their path in the finished run; its figures are in the run."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import pytest
import yaml
from helpers import papermill_from, params_file, run_cli
from test_notebook_params import complete_params

from gvbench_nb.runner import runs

pytestmark = pytest.mark.reliability


def files_of(run: Path) -> list[str]:
    return [p.relative_to(run).as_posix() for p in run.rglob("*") if p.is_file()]


def test_02_verify_under_papermill_f_records_the_file_given_and_keeps_its_figure_in_its_run(tmp_path):
    study = complete_params(tmp_path / "my" / "study")
    said = papermill_from(tmp_path, "02_verify", tmp_path / "02.ipynb", "-f", study, "-p", "method", "orb-nn")
    out = tmp_path / "my" / "study" / "out"
    [(run, manifest)] = runs.finished_runs(out)
    header = (run / "params.resolved.yaml").read_text()
    assert f"{study.resolve()} (sha256 {hashlib.sha256(study.read_bytes()).hexdigest()})" in header
    assert "Written by `notebooks/02_verify.ipynb`" in header and "python -m gvbench_nb run" not in header
    assert manifest["door"] == "02_verify"
    assert "inliers_orb-nn.png" in files_of(run) and not (out / "inliers_orb-nn.png").exists()
    assert f"of run {run.name}" in said and runs.BUILDING not in said


def test_runs_notebooks_and_records_name_the_params_in_the_finished_run(tmp_path, root, capsys):
    path = params_file(tmp_path)
    code, _, err = run_cli(capsys, "run", str(path))
    assert code == 0, err
    [(run, manifest)] = runs.finished_runs(tmp_path / "out")
    given = run / "params.resolved.yaml"
    for name in ("01_sequence.ipynb", "02_verify_orb-nn.ipynb", "03_evaluate.ipynb"):
        executed = json.loads((run / name).read_text())
        assert executed["metadata"]["papermill"]["parameters"]["params_file"] == str(given), name
        assert runs.BUILDING not in json.dumps(executed["cells"]), name  # sources and outputs
    records = [given, run / runs.MANIFEST, run / "orb-nn" / "run.json"]
    assert [p.name for p in records if runs.BUILDING in p.read_text()] == []
    assert {"inliers_orb-nn.png", "pr_curves.png", "sequence_examples.png"} <= set(files_of(run))
    assert yaml.safe_load(given.read_text())["output_dir"] == str(tmp_path / "out")
    assert f"{path} (sha256 {hashlib.sha256(path.read_bytes()).hexdigest()})" in given.read_text()
