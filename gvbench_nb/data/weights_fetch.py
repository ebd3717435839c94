"""``python -m gvbench_nb weights fetch NAME``: a checkpoint from its official URL (or a folder,
``--from``), SHA-256 checked, saved under the name the model loads.

None of the official sources publishes a SHA-256 for these files (the releases, the model
repositories and kornia's loaders give none), so the hash a fetch checks against is the one given
with ``--sha256``, else the one recorded beside the checkpoints at the first fetch of that file
(``RECORDED_NAME``): the first fetch trusts its source and says so, every later one is checked.
The download and its checks are ``data fetch``'s (``fetch._download``, ``fetch.sha256_of``).
"""

from __future__ import annotations

import json
import os
import shutil
import sys
import tarfile
import urllib.parse
from pathlib import Path
from typing import Any

from gvbench_nb.data import fetch
from gvbench_nb.io_utils import atomic_write_json
from gvbench_nb.protocol import weights

RECORDED_NAME = "gvbench-weights-sha256.json"  # file name -> SHA-256 of its first fetch


def recorded_hashes() -> dict[str, str]:
    try:
        recorded = json.loads((weights.checkpoints_dir() / RECORDED_NAME).read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return {}
    return recorded if isinstance(recorded, dict) else {}


def source_names(checkpoint: weights.Checkpoint) -> list[str]:
    """The names the file may have where it was downloaded to: the one the model loads, then each URL's."""
    return list(dict.fromkeys([checkpoint.file, *(Path(urllib.parse.urlsplit(u).path).name for u in checkpoint.urls)]))


def _bring(checkpoint: weights.Checkpoint, source_dir: Path | None, partial: Path) -> str:
    """The checkpoint's file (or archive) into ``partial``; returns where it came from."""
    if source_dir is not None:
        found = [source_dir / n for n in source_names(checkpoint) if (source_dir / n).is_file()]
        if not found:
            raise fetch.DataError(
                f"{source_dir} holds none of {', '.join(source_names(checkpoint))}; put the file downloaded from "
                f"{checkpoint.urls[0]} there"
            )
        shutil.copyfile(found[0], partial)
        return str(found[0])
    item = fetch.DataFile(path=checkpoint.file, source="", bytes=None, sha256="")
    problem = ""
    for url in checkpoint.urls:
        try:
            with _progress(checkpoint.file) as bar:
                fetch._download(url, partial, item, url, bar)
            return url
        except fetch.DataError as error:
            problem = str(error).split(";")[0]
    raise fetch.DataError(
        f"{problem}; download it on a connected machine and run python -m gvbench_nb weights fetch "
        f"{checkpoint.name} --from DIR with the file in DIR"
    )


def _progress(label: str) -> Any:
    from tqdm import tqdm

    return tqdm(unit="B", unit_scale=True, unit_divisor=1024, desc=label, file=sys.stderr, leave=False)


def _unpack(checkpoint: weights.Checkpoint, partial: Path) -> None:
    """Replace an archive in ``partial`` by the one member the model loads (read, never extracted whole)."""
    if not tarfile.is_tarfile(partial):
        return
    with tarfile.open(partial) as archive:
        member = next((m for m in archive.getmembers() if m.isfile() and Path(m.name).name == checkpoint.file), None)
        if member is None:
            raise fetch.DataError(f"the archive of {checkpoint.name} holds no {checkpoint.file}; {checkpoint.notes}")
        extracted = archive.extractfile(member)
        assert extracted is not None
        unpacked = partial.with_name(partial.name + ".member")
        with open(unpacked, "wb") as out:
            shutil.copyfileobj(extracted, out)
    os.replace(unpacked, partial)


def fetch_checkpoint(name: str, source_dir: str | os.PathLike[str] | None = None, sha256: str | None = None) -> str:
    """Place checkpoint ``name`` where its model loads it; returns what was done, in one line."""
    checkpoint = weights.get(name)
    target = weights.checkpoint_path(name)
    recorded = recorded_hashes()
    expected = (sha256 or recorded.get(checkpoint.file) or "").lower()
    whence = "given by --sha256" if sha256 else "recorded at its first fetch"
    if target.is_file() and expected and fetch.sha256_of(target) == expected:
        return f"{name}: {target} is there, SHA-256 {expected} ({whence}); licence: {checkpoint.licence}"
    target.parent.mkdir(parents=True, exist_ok=True)
    partial = fetch.partial_path(target)
    try:
        source = _bring(checkpoint, Path(source_dir).expanduser() if source_dir else None, partial)
        _unpack(checkpoint, partial)
        digest = fetch.sha256_of(partial)
        if expected and digest != expected:
            raise fetch.DataError(
                f"{checkpoint.file} from {source} has SHA-256 {digest}, not {expected} ({whence}), so it was not "
                "saved; fetch it again from the official URL or check the hash"
            )
    except BaseException:
        partial.unlink(missing_ok=True)
        raise
    os.replace(partial, target)
    if expected:
        return f"{name}: saved {target} from {source}, SHA-256 {digest} ({whence}); licence: {checkpoint.licence}"
    atomic_write_json(target.parent / RECORDED_NAME, {**recorded, checkpoint.file: digest})
    return (
        f"{name}: saved {target} from {source}, SHA-256 {digest} (no published hash: recorded in "
        f"{target.parent / RECORDED_NAME}, later fetches are checked against it); licence: {checkpoint.licence}"
    )
