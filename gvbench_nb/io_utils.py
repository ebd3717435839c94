"""Crash-safe file writes: a temporary file in the same folder, fsync, then rename.

A run killed mid-write leaves the previous file (or none), never a half-written one
that looks complete.
"""

from __future__ import annotations

import errno
import hashlib
import json
import os
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


def file_sha256(path: str | os.PathLike[str]) -> str:
    """SHA-256 of a file's bytes (pair files, published results)."""
    digest = hashlib.sha256()
    with open(path, "rb") as stream:
        for block in iter(lambda: stream.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def fsync_folder(folder: Path) -> None:
    """Make a rename in ``folder`` durable (a power cut could otherwise undo it)."""
    try:
        descriptor = os.open(folder, os.O_RDONLY)
    except OSError:  # some platforms cannot open folders; the rename is still atomic there
        return
    try:
        os.fsync(descriptor)
    except OSError:
        pass
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
        if os.path.exists(temporary):
            os.unlink(temporary)
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
