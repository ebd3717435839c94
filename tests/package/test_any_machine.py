"""No outcome depends on the machine: what `results` prints fits 100 columns whatever the CPU is
called and however many cores it has."""

from __future__ import annotations

import contextlib

import pytest
from helpers import in_process_notebooks, params_file, run_cli

from gvbench_nb import run_and_publish
from gvbench_nb.runner import concurrency


@pytest.mark.reliability
def test_results_fits_100_columns_whatever_the_cpu_is_called(tmp_path, root, capsys, monkeypatch):
    name = "Intel(R) Xeon(R) Platinum 8480+ Sapphire Rapids Engineering Sample v2 @ 2.80 GHz"
    assert len(name) == 80
    monkeypatch.setattr(concurrency, "cpu_name", lambda: name)
    monkeypatch.setattr(concurrency.os, "cpu_count", lambda: 1024)
    monkeypatch.setattr(run_and_publish, "execute_notebook", in_process_notebooks)
    monkeypatch.setattr(run_and_publish, "kernels_ahead", lambda count: contextlib.nullcontext())
    assert run_cli(capsys, "run", str(params_file(tmp_path)), "--limit", "3", "--jobs", "1")[0] == 0
    code, out, _ = run_cli(capsys, "results", str(tmp_path / "out"))
    machine = out.splitlines()[2]
    assert code == 0 and machine.startswith("device cpu (Intel(R) Xeon(R) Platinum") and "1024 cores" in machine
    assert max(map(len, out.splitlines()[1:])) <= 100, out  # all but the folder's path
