"""Progress written to a log file (not a terminal): a line every 30 s at most, as docs/usage.md says."""

from __future__ import annotations

import io

import pytest
import tqdm.std

from gvbench_nb.io_utils import BATCH_INTERVAL_SECONDS, progress_bar

MONITOR_SECONDS = 10  # tqdm's monitor thread wakes this often (tqdm.std.tqdm.monitor_interval)


class Log(io.StringIO):
    """A log file (no terminal) that notes the clock at each line written."""

    def __init__(self, clock: list[float]) -> None:
        super().__init__()
        self.clock, self.times = clock, []

    def write(self, text: str) -> int:
        self.times += [self.clock[0]] * text.count("\n")
        return super().write(text)


@pytest.mark.reliability
def test_a_bar_in_a_log_file_writes_a_line_every_30_s_at_most(monkeypatch):
    clock = [1000.0]
    monkeypatch.setattr(tqdm.std, "time", lambda: clock[0])  # the bars' clock, advanced by hand
    monkeypatch.setattr(tqdm.std.tqdm, "monitor_interval", 0)  # its rule is applied below, on this clock
    log = Log(clock)
    bar = progress_bar(total=1000, file=log, desc="match", unit="pair")
    for step in range(1, 1000):  # a pair every 0.2 s: 200 s
        clock[0] += 0.2
        bar.update()
        woken = step % (MONITOR_SECONDS * 5) == 0  # what the monitor does each time it wakes:
        if woken and bar.miniters > 1 and clock[0] - bar.last_print_t >= bar.maxinterval:
            bar.miniters = 1
            bar.refresh()
    bar.update()
    bar.close()
    gaps = [later - earlier for earlier, later in zip(log.times, log.times[1:-1])]  # the last: the bar closed
    assert len(log.times) >= 5 and min(gaps) >= BATCH_INTERVAL_SECONDS, log.getvalue()
