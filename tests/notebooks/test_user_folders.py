"""The tests touch nothing of the user's: the notebooks on their defaults, and the shipped params
files, write under ``$GVBENCH_OUTPUTS`` (a folder of the test session's), never the repository's outputs/."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from gvbench_nb import notebook
from gvbench_nb.reporting import execute
from gvbench_nb.runner import config


def repository_outputs() -> dict[str, int]:
    return {str(p): p.stat().st_mtime_ns for p in (config.PROJECT_ROOT / "outputs").rglob("*") if p.is_file()}


@pytest.mark.reliability
def test_the_shipped_params_write_under_the_sessions_outputs_folder():
    session_outputs = Path(os.environ["GVBENCH_OUTPUTS"])
    assert not session_outputs.is_relative_to(config.PROJECT_ROOT)
    for name in ("sample", "sample_retrieval", "gardens_point"):
        params = config.load_params(config.PROJECT_ROOT / "params" / f"{name}.yaml")
        assert Path(params["output_dir"]).is_relative_to(session_outputs), name
        assert not Path(params["pairs"]).is_relative_to(config.OUTPUTS_DIR), name
    assert Path(notebook.load_params(None)["output_dir"]) == session_outputs / "sample"


@pytest.mark.reliability
@pytest.mark.shared_outputs  # the session's outputs/sample
def test_a_notebook_on_its_defaults_writes_nothing_under_the_repositorys_outputs(tmp_path):
    before = repository_outputs()
    execute.execute_notebook("01_sequence.ipynb", tmp_path / "01_sequence.ipynb", {})  # as nbmake runs it
    assert repository_outputs() == before
    assert (Path(os.environ["GVBENCH_OUTPUTS"]) / "sample" / "sequence_examples.png").is_file()


@pytest.mark.reliability
def test_a_path_under_the_repositorys_outputs_moves_with_gvbench_outputs(tmp_path, monkeypatch):
    monkeypatch.chdir(config.PROJECT_ROOT / "notebooks")  # where the notebooks' defaults are read from
    moved = Path(os.environ["GVBENCH_OUTPUTS"]) / "sample" / "analysis"
    assert config.outputs_path("../outputs/sample/analysis") == moved
    assert config.outputs_path(tmp_path / "mine") == tmp_path / "mine"  # elsewhere: as given
    monkeypatch.delenv("GVBENCH_OUTPUTS")
    assert config.outputs_path("../outputs/sample") == Path("../outputs/sample")


def test_gvbench_outputs_naming_a_file_is_one_sentence(tmp_path, monkeypatch):
    (tmp_path / "a-file").write_text("")
    monkeypatch.setenv("GVBENCH_OUTPUTS", str(tmp_path / "a-file"))
    with pytest.raises(config.SettingError, match=r"GVBENCH_OUTPUTS \(outputs/\) must name a folder"):
        config.check_environment()
