"""A notebook parameter papermill passes that the notebook does not declare is refused in the first
cell, in one sentence with "did you mean", as the command line refuses a misspelled option."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

from gvbench_nb import notebook
from gvbench_nb.reporting import execute
from gvbench_nb.runner import config


@pytest.mark.reliability
def test_papermill_refuses_a_misspelled_parameter_of_a_stage_notebook_before_any_work(tmp_path):
    notebook_path = config.PROJECT_ROOT / "notebooks" / "02_verify.ipynb"
    out = tmp_path / "out"
    done = subprocess.run(
        [sys.executable, "-m", "papermill", str(notebook_path), str(tmp_path / "o.ipynb")]
        + ["-p", "limt", "10", "-p", "output_dir", str(out)],
        capture_output=True,
        text=True,
        timeout=600,
        env={**os.environ, "PYTHONPATH": str(config.PROJECT_ROOT)},
    )
    assert done.returncode != 0
    assert "ParameterError: unknown notebook parameter(s) 'limt' (did you mean 'limit'?); this notebook's:" in (
        done.stderr
    )
    assert not out.exists()


@pytest.mark.reliability
def test_an_analysis_notebook_refuses_a_misspelled_parameter_in_one_sentence(tmp_path):
    with pytest.raises(execute.NotebookFailedError) as failure:
        execute.execute_notebook(
            "analysis_inlier_histograms.ipynb",
            tmp_path / "histograms.ipynb",
            {"output_dirs": [str(tmp_path / "none")], "ouptut_dir": str(tmp_path / "figures")},
        )
    assert failure.value.ename == "ParameterError"
    assert failure.value.evalue.startswith("unknown notebook parameter(s) 'ouptut_dir' (did you mean 'output_dir'?)")
    assert "\n" not in failure.value.evalue and not (tmp_path / "figures").exists()


def test_the_parameters_a_notebook_declares_pass_and_others_name_the_closest():
    declared = {"limit": int, "method": str}
    injected = "# Parameters\nlimit = 3\nmethod = 'orb-nn'\n"
    notebook.check_parameters({"__annotations__": declared, "In": ["", injected], "limit": 3, "method": "orb-nn"})
    with pytest.raises(notebook.ParameterError) as error:
        notebook.check_parameters({"__annotations__": declared, "In": ["", injected + "metod = 'x'\nzz = 1\n"]})
    assert str(error.value) == (
        "unknown notebook parameter(s) 'metod' (did you mean 'method'?), 'zz'; this notebook's: limit, method"
    )
