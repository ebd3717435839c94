"""What every layer shares for input and output: crash-safe file writes (a temporary file in the
same folder, fsync, then rename: a run killed mid-write leaves the previous file or none), the
bounded whole numbers and did-you-mean hints of options and params, and progress bars."""

from __future__ import annotations

import argparse
import contextlib
import difflib
import errno
import hashlib
import json
import os
import sys
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

from gvbench_nb import GVBenchError

if TYPE_CHECKING:  # pandas is imported by whoever passes a frame
    import pandas as pd

_UMASK = os.umask(0o022)
os.umask(_UMASK)  # read once: os.umask can only be read by setting it


class WriteFailedError(GVBenchError, OSError):
    """A file could not be written for want of room (disk full, quota, file size limit)."""

    def __str__(self) -> str:
        return str(self.strerror)


# A disk or quota that is full, or a file size limit (EFBIG: Python ignores SIGXFSZ).
WRITE_FAILURES = {errno.ENOSPC, errno.EDQUOT, errno.EFBIG}


def hash_file(path: str | os.PathLike[str], digest: Any) -> str:
    """The hex of ``digest`` (a ``hashlib`` object) once it took a file's bytes, read a block at a time."""
    with open(path, "rb") as stream:
        for block in iter(lambda: stream.read(1 << 20), b""):
            digest.update(block)
    return str(digest.hexdigest())


def file_sha256(path: str | os.PathLike[str]) -> str:
    """SHA-256 of a file's bytes (pair files, published results)."""
    return hash_file(path, hashlib.sha256())


def fsync_folder(folder: Path) -> None:
    """Make a rename in ``folder`` durable (a power cut could otherwise undo it)."""
    with contextlib.suppress(OSError):  # some platforms cannot open folders; the rename is still atomic there
        descriptor = os.open(folder, os.O_RDONLY)
        try:
            os.fsync(descriptor)
        finally:
            os.close(descriptor)


def _atomic_write(path: Path, write: Callable[[Path], object]) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    handle, temporary = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    os.close(handle)
    os.chmod(temporary, 0o666 & ~_UMASK)  # mkstemp makes 0600; results are for everyone who may read
    try:
        write(Path(temporary))
        with open(temporary, "rb") as stream:
            os.fsync(stream.fileno())
        os.replace(temporary, path)
        fsync_folder(path.parent)
    except BaseException as error:
        Path(temporary).unlink(missing_ok=True)
        if isinstance(error, OSError) and error.errno in WRITE_FAILURES:
            raise WriteFailedError(
                error.errno,
                f"cannot write {path} ({error.strerror}); free disk space (or raise the quota or file size "
                "limit) and run again: the previous file, if any, is kept",
            ) from error
        raise
    return path


def atomic_write_text(path: Path, text: str) -> Path:
    return _atomic_write(path, lambda tmp: tmp.write_text(text, encoding="utf-8"))


def atomic_write_json(path: Path, data: Any) -> Path:
    return atomic_write_text(path, json.dumps(data, indent=2, sort_keys=True, default=str) + "\n")


def atomic_write_csv(path: Path, frame: pd.DataFrame) -> Path:
    # Fixed float format so two runs on the same input give byte-identical files.
    return _atomic_write(path, lambda tmp: frame.to_csv(tmp, index=False, float_format="%.6g", lineterminator="\n"))


def is_whole_number(value: Any) -> bool:
    """An int given in a params file or from code (YAML's ``yes`` is a bool, not 1)."""
    return isinstance(value, int) and not isinstance(value, bool)


def whole_number_at_least(text: str, minimum: int, what: str) -> int:
    """``text`` as a whole number of at least ``minimum``, else argparse's error: ``must be {what}``."""
    try:
        value = int(text)
    except ValueError:
        value = minimum - 1
    if value < minimum:
        raise argparse.ArgumentTypeError(f"must be {what}, got {text!r}")
    return value


def unknown_keys_hint(unknown: list[str], valid: list[str]) -> str:
    """``'limt' (did you mean 'limit'?), 'x'``: each unknown key with its closest valid one."""
    hints = []
    for key in unknown:
        close = difflib.get_close_matches(key, valid, n=1)
        hints.append(f"{key!r}" + (f" (did you mean {close[0]!r}?)" if close else ""))
    return ", ".join(hints)


def add_described_command(commands: Any, name: str, summary: str, description: str, epilog: str) -> Any:
    """A sub-command whose description and examples keep their line breaks in ``--help``."""
    raw = argparse.RawDescriptionHelpFormatter
    return commands.add_parser(name, help=summary, description=description, epilog=epilog, formatter_class=raw)


class SuggestingParser(argparse.ArgumentParser):
    """argparse's parser, with a did-you-mean for a mistyped command or choice (``rn`` -> ``run``).
    Its sub-command parsers are of this class too (argparse makes them of their parent's)."""

    def _check_value(self, action: argparse.Action, value: object) -> None:
        choices = action.choices
        if choices is not None and value not in choices:
            close = difflib.get_close_matches(str(value), [str(c) for c in choices], n=1)
            if close:
                known = ", ".join(map(str, choices))
                raise argparse.ArgumentError(
                    action, f"invalid choice: {value!r}; did you mean {close[0]!r}? (choose from {known})"
                )
        super()._check_value(action, value)


# Progress bars that fit where they run: a widget in JupyterLab, a bar redrawn in a terminal, and in
# a file or a batch-executed notebook a line every half minute at most (a few lines a bar in a log).
BATCH_INTERVAL_SECONDS = 30.0


def interactive_kernel() -> bool:
    """A kernel a Jupyter server started (it sets JPY_SESSION_NAME); not a terminal, papermill's or nbmake's."""
    return "ipykernel" in sys.modules and "JPY_SESSION_NAME" in os.environ


def progress_bar(iterable: Any = None, **options: Any) -> Any:
    """``tqdm(iterable, **options)`` for where it runs: ``tqdm.auto`` (a widget) in JupyterLab;
    elsewhere plain tqdm, redrawn at most every ``BATCH_INTERVAL_SECONDS`` unless it writes to a terminal."""
    if interactive_kernel():
        from tqdm.auto import tqdm as auto_tqdm

        return auto_tqdm(iterable, **options)
    from tqdm import tqdm

    stream = options.get("file") or sys.stderr
    if not getattr(stream, "isatty", lambda: False)():
        options.setdefault("mininterval", BATCH_INTERVAL_SECONDS)
        options.setdefault("maxinterval", BATCH_INTERVAL_SECONDS)  # tqdm's monitor redraws a slow bar after it
        options["file"] = _LinePerRedraw(stream)
    return tqdm(iterable, **options)


class _LinePerRedraw:
    """A file or pipe under a progress bar: each redraw is a whole line (no carriage returns), so the
    status lines written between two redraws start lines of their own."""

    def __init__(self, stream: Any):
        self._stream, self._last = stream, ""

    def write(self, text: str) -> int:
        line = text.replace("\r", "").rstrip()
        if line and line != self._last:  # closing redraws the last state once more
            self._stream.write(line + "\n")
            self._last = line
        return len(text)

    def __getattr__(self, name: str) -> Any:  # flush, encoding, ...: the stream's
        return getattr(self._stream, name)
