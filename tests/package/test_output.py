"""Output fits where it runs: progress bars as widgets, sparse lines or terminal bars; status lines to
the current stdout, silenced by --quiet while the asked-for table stays."""

from __future__ import annotations

import io
import logging
import sys
import types

from gvbench_nb import cli, set_log_level
from gvbench_nb import io_utils as progress


class Terminal(io.StringIO):
    def isatty(self) -> bool:
        return True


def test_a_bar_into_a_file_or_a_batch_kernel_writes_a_line_every_half_minute_at_most(monkeypatch):
    monkeypatch.delenv("JPY_SESSION_NAME", raising=False)
    log = io.StringIO()
    bar = progress.progress_bar(total=5000, file=log)
    assert bar.mininterval == progress.BATCH_INTERVAL_SECONDS
    for _ in range(5000):
        bar.update()
    bar.close()
    states = [line for line in log.getvalue().replace("\n", "\r").split("\r") if line.strip()]
    assert len(states) <= 3 and states[-1].startswith("100%"), states
    assert progress.progress_bar(total=1, file=Terminal()).mininterval < 1  # a terminal redraws as usual


def test_a_kernel_jupyterlab_started_gets_tqdm_auto(monkeypatch):
    made = []
    monkeypatch.setitem(sys.modules, "tqdm.auto", types.SimpleNamespace(tqdm=lambda *a, **k: made.append(k)))
    monkeypatch.setitem(sys.modules, "ipykernel", types.ModuleType("ipykernel"))
    monkeypatch.setenv("JPY_SESSION_NAME", "explore_pairs.ipynb")
    progress.progress_bar(total=3, desc="extract")
    assert made == [{"total": 3, "desc": "extract"}]  # the widget, at tqdm's own update rate
    monkeypatch.delenv("JPY_SESSION_NAME")  # papermill's and nbmake's kernels: plain text, few lines
    assert progress.progress_bar(total=3, file=io.StringIO()).mininterval == progress.BATCH_INTERVAL_SECONDS
    assert len(made) == 1


def test_status_lines_reach_the_current_stdout_and_quiet_keeps_the_table(capsys):
    try:
        assert cli.main(["methods"]) == 0
        loud = capsys.readouterr().out
        assert cli.main(["--quiet", "methods"]) == 0
        quiet = capsys.readouterr().out
    finally:
        set_log_level(logging.INFO)
    assert "run any of them:" in loud and "run any of them:" not in quiet
    assert quiet.splitlines()[0] == loud.splitlines()[0] and "sift-nn" in quiet  # the table itself
