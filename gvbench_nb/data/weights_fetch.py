"""``weights fetch NAME``: a checkpoint from its official URL (or ``--from`` a folder) under the name the model loads.
No source publishes a SHA-256: the one checked is ``--sha256``, else the one recorded at the file's first fetch."""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import tarfile
import tempfile
from pathlib import Path
from urllib.parse import urlsplit

import pooch
import requests

from gvbench_nb.data import fetch
from gvbench_nb.io_utils import atomic_write_json, file_sha256
from gvbench_nb.protocol import weights

RECORDED_NAME = "gvbench-weights-sha256.json"  # file name -> SHA-256 of its first fetch


def recorded_hashes() -> dict[str, str]:
    with contextlib.suppress(OSError, ValueError):
        recorded = json.loads((weights.checkpoints_dir() / RECORDED_NAME).read_text(encoding="utf-8"))
        return recorded if isinstance(recorded, dict) else {}
    return {}


def _bring(checkpoint: weights.Checkpoint, source_dir: Path | None, work: Path) -> tuple[Path, str]:
    """The checkpoint's file (or archive) copied or downloaded into ``work``, and where it came from."""
    if source_dir is not None:  # the file under the name the model loads, or under a URL's
        names = list(dict.fromkeys([checkpoint.file, *(Path(urlsplit(u).path).name for u in checkpoint.urls)]))
        found = [source_dir / n for n in names if (source_dir / n).is_file()]
        if not found:
            hint = f"put the file downloaded from {checkpoint.urls[0]} there"
            raise fetch.DataError(f"{source_dir} holds none of {', '.join(names)}; {hint}")
        return Path(shutil.copyfile(found[0], work / "file")), str(found[0])
    problem = ""
    for url in checkpoint.urls:  # no hash for pooch: the one checked is the model's file's, which an archive holds
        files = pooch.create(work, url, registry={"file": None}, urls={"file": url}, retry_if_failed=fetch.ATTEMPTS - 1)
        try:
            return Path(files.fetch("file", downloader=fetch.downloader(url, progressbar=True))), url
        except (requests.RequestException, FileNotFoundError) as error:
            problem = f"cannot download {url} ({fetch.root_cause(error)})"
    raise fetch.DataError(
        f"{problem}; download it on a connected machine and run python -m gvbench_nb weights fetch "
        f"{checkpoint.name} --from DIR with the file in DIR"
    )


def fetch_checkpoint(name: str, source_dir: str | os.PathLike[str] | None = None, sha256: str | None = None) -> str:
    """Place checkpoint ``name`` where its model loads it; returns what was done, in one line."""
    checkpoint, target, recorded = weights.get(name), weights.checkpoint_path(name), recorded_hashes()
    expected = (sha256 or recorded.get(checkpoint.file) or "").lower()
    whence = "given by --sha256" if sha256 else "recorded at its first fetch"
    if target.is_file() and expected and file_sha256(target) == expected:
        return f"{name}: {target} is there, SHA-256 {expected} ({whence}); licence: {checkpoint.licence}"
    target.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(dir=target.parent, prefix=".fetch-") as work:  # gone whatever happens
        path, source = _bring(checkpoint, Path(source_dir).expanduser() if source_dir else None, Path(work))
        if tarfile.is_tarfile(path):  # the one member the model loads, extracted alone
            with tarfile.open(path) as archive:
                found = [m for m in archive.getmembers() if m.isfile() and Path(m.name).name == checkpoint.file]
                if not found:
                    raise fetch.DataError(f"the archive of {name} holds no {checkpoint.file}; {checkpoint.notes}")
                found[0].name, path = checkpoint.file, Path(work) / checkpoint.file
                archive.extract(found[0], work, filter="data")
        digest = file_sha256(path)
        if expected and digest != expected:
            hint = f"({whence}), so it was not saved; fetch it again from the official URL or check the hash"
            raise fetch.DataError(f"{checkpoint.file} from {source} has SHA-256 {digest}, not {expected} {hint}")
        os.replace(path, target)  # atomic: the final name only ever holds a checked file
    if not expected:
        atomic_write_json(target.parent / RECORDED_NAME, {**recorded, checkpoint.file: digest})
        whence = f"no published hash: recorded in {target.parent / RECORDED_NAME}, later fetches are checked against it"
    return f"{name}: saved {target} from {source}, SHA-256 {digest} ({whence}); licence: {checkpoint.licence}"
