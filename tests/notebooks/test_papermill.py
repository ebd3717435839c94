"""The stage notebooks under plain papermill from any folder: ``-p params_file``, ``-f PARAMS.yaml``
or no parameters (the sample); every parameter typed."""

from __future__ import annotations

import os
import subprocess
from pathlib import Path

import papermill
import pytest
from helpers import papermill_process

from gvbench_nb import notebook
from gvbench_nb.runner import config, method_outputs, runs

STAGES = ("01_sequence", "02_verify", "03_evaluate")
NOTEBOOKS = config.PROJECT_ROOT / "notebooks"


def test_the_stage_notebooks_take_every_params_key_as_a_typed_parameter():
    keys = {"params_file", *config.REQUIRED_KEYS, *config.OPTIONAL_KEYS}
    for stage in STAGES:
        parameters = papermill.inspect_notebook(str(NOTEBOOKS / f"{stage}.ipynb"))
        assert set(parameters) >= keys, stage
        untyped = [name for name, p in parameters.items() if p["inferred_type_name"] in ("None", "NoneType")]
        assert untyped == [], stage


def test_a_params_files_keys_read_as_that_file_from_any_folder(monkeypatch, tmp_path):
    monkeypatch.chdir(tmp_path)
    gardens = config.PROJECT_ROOT / "params" / "gardens_point.yaml"
    keys = config.read_yaml_mapping(gardens)  # what `papermill -f params/gardens_point.yaml` passes
    as_keys = notebook.load_params(None, **keys, limit=4)
    as_file = config.load_params(gardens, limit=4)
    assert {k: as_keys[k] for k in config.PATH_KEYS} == {k: as_file[k] for k in config.PATH_KEYS}
    assert as_keys["pairs"] == str(config.outputs_path(config.OUTPUTS_DIR / "pairs" / "gardens_point.txt"))
    assert as_keys["pairs_builder"] == "frame_tolerance" and as_keys["limit"] == 4
    # No parameters: the repository's sample, wherever the notebook runs.
    assert notebook.load_params(None)["params_file"] == str(config.PROJECT_ROOT / "params" / "sample.yaml")
    # Every key, of a sequence no shipped file is: those keys, relative paths read from the working folder.
    assert notebook.load_params(None, **{**keys, "sequence": "mine"})["pairs"] == str(
        tmp_path.parent / "outputs" / "pairs" / "gardens_point.txt"
    )


def papermill_cli(cwd: Path, stage: str, output: Path, *arguments: str) -> subprocess.CompletedProcess:
    done = papermill_process(cwd, os.path.relpath(NOTEBOOKS / f"{stage}.ipynb", cwd), output, *arguments)
    assert "unknown parameter" not in done.stderr
    return done


@pytest.mark.slow
@pytest.mark.shared_outputs  # the sample renders its images into outputs/ ($GVBENCH_OUTPUTS)
@pytest.mark.parametrize("folder", ["repository", "tmp"])
def test_papermill_runs_the_stage_notebooks_as_they_are_from_the_repository_and_tmp(folder, tmp_path):
    cwd = config.PROJECT_ROOT if folder == "repository" else tmp_path
    params = os.path.relpath(config.PROJECT_ROOT / "params" / "sample.yaml", cwd)
    out, cache = tmp_path / "out", tmp_path / "cache"
    options = ["-p", "method", "orb-nn", "-p", "limit", "4", "-p", "output_dir", str(out)]
    elsewhere = [*options, "-p", "cache_dir", str(cache)]
    papermill_cli(cwd, "02_verify", tmp_path / "p.ipynb", "-p", "params_file", params, *elsewhere)
    written = (method_outputs.method_dir(out, "orb-nn") / "pairs.csv").read_bytes()
    assert written.count(b"\n") == 1 + 4
    papermill_cli(cwd, "02_verify", tmp_path / "f.ipynb", "-f", params, *elsewhere)
    # The same params: a run of its own, its table made from the same stores.
    assert len(runs.finished_runs(out)) == 2
    assert (method_outputs.method_dir(out, "orb-nn") / "pairs.csv").read_bytes() == written
    papermill_cli(cwd, "01_sequence", tmp_path / "none.ipynb")  # no parameters: the sample
    sample_out = Path(config.load_params(config.PROJECT_ROOT / "params" / "sample.yaml")["output_dir"])
    assert (sample_out / "sequence_examples.png").is_file()
