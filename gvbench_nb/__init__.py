"""gvbench-nb: geometric verification of loop closures, benchmarked as in GV-Bench.

Stages (one function each): ``sequence_build.prepare_sequence`` -> ``image_features.extract_features``
-> ``pair_matching.match_and_verify`` -> ``method_runs.pairs_table`` -> ``scoring.evaluate``.
"""

import logging
import sys

__version__ = "0.1.0"


class GVBenchError(Exception):
    """An error the user can cause (params, pairs, images, weights, caches, output folders): the
    command line prints its message as one sentence, without a traceback."""

    exit_code = 2


class _CurrentStreamHandler(logging.StreamHandler):
    """Status lines to sys.stdout, warnings and errors to sys.stderr, as they are when a line is
    written: pytest's capture and a notebook's cell output see them."""

    def emit(self, record: logging.LogRecord) -> None:
        self.stream = sys.stderr if record.levelno >= logging.WARNING else sys.stdout
        if not (terminal_bars_drawn() and self.stream.isatty()):
            super().emit(record)
            return
        from tqdm import tqdm

        with tqdm.external_write_mode(file=self.stream):  # the bar is cleared, the line written, the bar redrawn
            super().emit(record)


def terminal_bars_drawn() -> bool:
    """Whether a progress bar may stand unfinished on a terminal's line (elsewhere ``io_utils.progress_bar``
    ends each redraw's line); tqdm draws none before it is imported."""
    tqdm = sys.modules.get("tqdm")
    return any(not bar.disable for bar in list(getattr(getattr(tqdm, "tqdm", None), "_instances", ())))


def set_log_level(level: int) -> None:
    """The package's status lines at ``level`` and above (``--quiet``: warnings, ``--verbose``: debug)."""
    log = logging.getLogger(__name__)
    if not any(isinstance(h, _CurrentStreamHandler) for h in log.handlers):
        log.addHandler(_CurrentStreamHandler())
        log.propagate = False  # one copy of each line, whatever the root logger does
    log.setLevel(level)


set_log_level(logging.INFO)
