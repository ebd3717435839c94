"""The run record (``gvbench-run.json``): the SHA-256 of every file the package published in an
output folder, so a file it did not write is never overwritten. One run writes a folder at a time
(``FolderLock``), builds in a stage and publishes it whole (``publish``) or not at all."""

from __future__ import annotations

import contextlib
import datetime as _dt
import json
import os
import platform
import secrets
import shutil
import sys
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path
from typing import Any, TypeVar

from gvbench_nb import GVBenchError, __version__
from gvbench_nb.io_utils import atomic_write_json, file_sha256, fsync_folder

T = TypeVar("T")
RECORD_NAME = "gvbench-run.json"
READ_WAIT_SECONDS = 60  # how long a reader waits for runs publishing into a folder it reads
LOCK_NAME = ".gvbench.lock"  # held by the one run writing the folder
HOLDER_NAME = ".gvbench-running.json"  # who holds the lock: pid, host, command, start
RECORD_LOCK_NAME = ".gvbench-record.lock"  # held for the moment the record is read and rewritten
STAGE_PREFIX = ".run-"
STAGE_MARKER = ".stage.json"  # in a stage: the folder it will be published into (working state)
PACKAGE = "gvbench-nb"
# The names the package writes in an output folder besides its record.
OWN_NAMES = (RECORD_NAME, LOCK_NAME, HOLDER_NAME, RECORD_LOCK_NAME)


class RecordError(GVBenchError, ValueError):
    """An output folder cannot be written: not the package's, held by another run, or changed by hand."""


def now() -> str:
    return _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")


def read_record(folder: str | os.PathLike[str]) -> dict[str, Any] | None:
    """The folder's record, or None when it has none (or one the package did not write)."""
    try:
        record = json.loads((Path(folder) / RECORD_NAME).read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    if not isinstance(record, dict) or record.get("package") != PACKAGE:
        return None
    record.setdefault("files", {})
    record.setdefault("methods", {})
    return record


def is_stage(folder: str | os.PathLike[str]) -> bool:
    return (Path(folder) / STAGE_MARKER).is_file()


def _shown(names: list[str], at_most: int = 3) -> str:
    shown = ", ".join(sorted(names)[:at_most])
    return shown + (f" and {len(names) - at_most} more" if len(names) > at_most else "")


def check_owned(folder: str | os.PathLike[str]) -> None:
    """Raise ``RecordError`` unless ``folder`` is missing, empty, a stage, or holds a record."""
    folder = Path(folder)
    if not folder.is_dir() or is_stage(folder) or read_record(folder) is not None:
        return
    entries = [p.name for p in folder.iterdir()]
    if entries:
        raise RecordError(
            f"output folder {folder} is not empty ({_shown(entries)}) and holds no {RECORD_NAME}, so its files are "
            "not gvbench-nb's to replace; give a new or empty output_dir (or --output-dir), or the folder of an "
            "earlier run"
        )


def check_no_foreign_files(folder: str | os.PathLike[str], names: Iterable[str]) -> None:
    """Refuse when any of ``names`` (relative to ``folder``) is present and the package did not write it, or it
    changed since."""
    folder = Path(folder)
    record = read_record(folder) or {"files": {}}
    being_written = set(record.get("pending", []))  # by a writer that may have been killed half way
    foreign = []
    for name in names:
        path = folder / name
        if not (path.exists() or path.is_symlink()) or (name in being_written and path.is_file()):
            continue
        if path.is_symlink() or not path.is_file() or record["files"].get(name) != file_sha256(path):
            foreign.append(name)
    if foreign:
        raise RecordError(
            f"{Path(folder)} holds {_shown(foreign)}, which gvbench-nb did not write there (or which changed since "
            "it did); move them away, or give another output_dir (or --output-dir)"
        )


@contextlib.contextmanager
def editing(folder: str | os.PathLike[str]) -> Iterator[dict[str, Any]]:
    """The folder's record (a new one when it has none), rewritten atomically after the block."""
    from filelock import FileLock

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    with FileLock(str(folder / RECORD_LOCK_NAME), timeout=60):
        record = read_record(folder) or {
            "package": PACKAGE,
            "created_at": now(),
            "state": "published",
            "files": {},
            "methods": {},
        }
        yield record
        record["version"] = __version__
        atomic_write_json(folder / RECORD_NAME, record)


def owning_folder(path: str | os.PathLike[str]) -> Path | None:
    """The output folder with a record holding ``path`` (its folder or the one above); None for a stage."""
    path = Path(path)
    for folder in (path.parent, path.parent.parent):
        if is_stage(folder):
            return None
        if read_record(folder) is not None:
            return folder
    return None


def register(paths: Iterable[str | os.PathLike[str]]) -> None:
    """Record files just written in place (a notebook run outside ``run``) so a later run knows them."""
    by_folder: dict[Path, list[Path]] = {}
    for path in map(Path, paths):
        folder = owning_folder(path)
        if folder is not None:
            by_folder.setdefault(folder, []).append(path)
    for folder, written in by_folder.items():
        with editing(folder) as record:
            for path in written:
                if path.is_file():
                    record["files"][path.relative_to(folder).as_posix()] = file_sha256(path)


def claim(folder: str | os.PathLike[str]) -> None:
    """Give ``folder`` a record unless it has one or is a stage (``run`` checks ``check_owned`` first)."""
    folder = Path(folder)
    if is_stage(folder) or read_record(folder) is not None:
        return
    with editing(folder):  # under the record's lock: two writers claiming at once make one record
        pass


@contextlib.contextmanager
def pending(folder: str | os.PathLike[str], names: list[str]) -> Iterator[None]:
    """Mark ``names`` as being written in ``folder``, so a killed writer's files stay ours."""
    with editing(folder) as record:
        record["pending"] = sorted({*record.get("pending", []), *names})
    yield
    with editing(folder) as record:
        record["pending"] = [n for n in record.get("pending", []) if n not in names]
        for name in names:
            if (Path(folder) / name).is_file():
                record["files"][name] = file_sha256(Path(folder) / name)
        if not record["pending"]:
            del record["pending"]


def save_checked(path: str | os.PathLike[str], write: Any) -> Path:
    """``write(path)`` unless it would overwrite a file we did not write; the file is then recorded."""
    path = Path(path)
    folder = owning_folder(path)
    if folder is None:
        write(path)
        return path
    name = path.relative_to(folder).as_posix()
    check_no_foreign_files(folder, [name])
    with pending(folder, [name]):
        write(path)
    return path


# Folders whose lock this process holds, counted: a run's own steps take it again without waiting.
_held: dict[Path, list[Any]] = {}  # folder -> [count, the FileLock that holds it]


class FolderLock:
    """The lock of one output folder, held by the run writing it (freed when its process ends)."""

    def __init__(self, folder: str | os.PathLike[str]):
        from filelock import FileLock

        self.folder = Path(folder).resolve()
        self._lock = FileLock(str(self.folder / LOCK_NAME))

    def acquire(self, wait_seconds: float = 0) -> None:
        from filelock import Timeout

        if self.folder in _held:
            _held[self.folder][0] += 1
            return
        self.folder.mkdir(parents=True, exist_ok=True)
        try:
            self._lock.acquire(timeout=wait_seconds)
        except Timeout:
            holder = _holder(self.folder)
            who = f"pid {holder.get('pid')} on {holder.get('host')}, started {holder.get('started_at')}"
            raise RecordError(
                f"another run is writing {self.folder} ({who if holder else 'its holder is not known'}); wait for it "
                "to finish or give another output_dir (or --output-dir)"
            ) from None
        atomic_write_json(
            self.folder / HOLDER_NAME,
            {"pid": os.getpid(), "host": platform.node(), "started_at": now(), "command": " ".join(sys.argv)},
        )
        _held[self.folder] = [1, self._lock]

    def release(self) -> None:
        held = _held[self.folder]
        held[0] -= 1
        if held[0]:
            return
        del _held[self.folder]
        (self.folder / HOLDER_NAME).unlink(missing_ok=True)
        held[1].release()

    def __enter__(self) -> FolderLock:
        self.acquire()
        return self

    def __exit__(self, *exc: object) -> None:
        self.release()


def _holder(folder: Path) -> dict[str, Any]:
    try:
        holder = json.loads((folder / HOLDER_NAME).read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return {}
    return holder if isinstance(holder, dict) else {}


def running(folder: str | os.PathLike[str]) -> dict[str, Any] | None:
    """Who is writing ``folder`` now, or None (a holder file left by a killed run is not a run)."""
    from filelock import FileLock, Timeout

    folder = Path(folder)
    if not (folder / HOLDER_NAME).is_file():
        return None
    probe = FileLock(str(folder / LOCK_NAME))
    try:
        probe.acquire(timeout=0)
    except Timeout:
        return _holder(folder)
    probe.release()
    return None


def kept_methods(
    output_dir: Path, methods: list[str], binding: dict[str, Any]
) -> tuple[list[str], dict[str, dict[str, Any]]]:
    """The methods kept from earlier runs, with their bindings; refused when bound to other inputs."""
    published = (read_record(output_dir) or {}).get("methods", {})
    kept = {m: {k: v for k, v in entry.items() if k != "files"} for m, entry in published.items() if m not in methods}
    other = [  # an imported method read no images (images_digest None): its pairs and labels bind it
        m
        for m, entry in kept.items()
        if entry.get("pairs_digest") != binding["pairs_digest"]
        or entry.get("images_digest") not in (None, binding["images_digest"])
    ]
    if other:
        raise RecordError(
            f"{output_dir} holds results of {', '.join(other)} computed on other pairs, labels or images than this "
            f"run's ({binding['pairs_file']}); run them again with this run (--methods "
            f"{','.join([*methods, *other])}) or give another --output-dir"
        )
    return list(kept), kept


# ---------------------------------------------------------------------- stage --
def open_stage(folder: str | os.PathLike[str]) -> Path:
    """A new stage in ``folder``; stopped runs' stages are deleted first (the lock holder's to remove)."""
    folder = Path(folder)
    for old in folder.glob(f"{STAGE_PREFIX}*"):
        if old.is_dir() and is_stage(old):
            shutil.rmtree(old, ignore_errors=True)
    # Unique also for two runs of one process within a second (the timers tell their work apart by it).
    run_id = _dt.datetime.now(_dt.timezone.utc).strftime("%Y%m%dT%H%M%SZ") + f"-{os.getpid()}-{secrets.token_hex(3)}"
    stage = folder / f"{STAGE_PREFIX}{run_id}"
    stage.mkdir(parents=True)
    atomic_write_json(stage / STAGE_MARKER, {"output_dir": str(folder), "run_id": run_id, "started_at": now()})
    return stage


def stage_run_id(stage: str | os.PathLike[str]) -> str | None:
    try:
        return str(json.loads((Path(stage) / STAGE_MARKER).read_text(encoding="utf-8"))["run_id"])
    except (OSError, ValueError, KeyError, TypeError):
        return None


def staged_files(stage: Path) -> list[str]:
    """The files a stage will publish (relative paths), its working state left out."""
    return [
        path.relative_to(stage).as_posix()
        for path in sorted(stage.rglob("*"))
        if path.is_file() and path.name != STAGE_MARKER and not path.name.startswith(".write-check-")
    ]


def carry(folder: Path, stage: Path, methods: Iterable[str]) -> list[str]:
    """Copy the kept ``methods``' files into the stage (the folder's whole next state); those carried."""
    record = read_record(folder) or {"methods": {}, "files": {}}
    carried = []
    for method in methods:
        if method not in record["methods"]:
            continue
        for name in method_files(record["files"], method):
            target = stage / name
            target.parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(folder / name, target)
        carried.append(method)
    return carried


def method_files(files: Iterable[str], method: str) -> list[str]:
    """Of a run's published files, those that belong to one method (kept with it by later runs)."""
    return [
        name
        for name in files
        if name.startswith(f"{method}/") or name in (f"02_verify_{method}.ipynb", f"inliers_{method}.png")
    ]


def drop_earlier_run_files(folder: Path, record: dict[str, Any], method: str, current: Iterable[str]) -> None:
    """Delete, and strike from ``record``, the files recorded in a method's folder that are not among its
    ``current`` files: written in place from an earlier run of it (an export), they no longer are its results."""
    current = set(current)
    for name in [n for n in record["files"] if n.startswith(f"{method}/") and n not in current]:
        (folder / name).unlink(missing_ok=True)
        record["files"].pop(name)


def publish(folder: Path, stage: Path, methods: dict[str, dict[str, Any]]) -> list[str]:
    """Move a finished stage into ``folder``; the record says ``publishing`` meanwhile, so a reader never
    takes a half-moved folder for results (``finish_publishing`` completes a killed move)."""
    check_no_foreign_files(folder, staged_files(stage))
    with editing(folder) as record:
        record["state"] = "publishing"
        record["stage"] = stage.name
        record["next"] = {"files": staged_files(stage), "methods": methods, "run_id": stage_run_id(stage)}
    return _move_and_record(folder, stage)


def _move_and_record(folder: Path, stage: Path) -> list[str]:
    record = read_record(folder)
    assert record is not None and record.get("state") == "publishing"
    files, methods = record["next"]["files"], record["next"]["methods"]
    for name in files:
        if (stage / name).is_file():  # a resumed move finds some files moved already
            target = folder / name
            target.parent.mkdir(parents=True, exist_ok=True)
            os.replace(stage / name, target)
    fsync_folder(folder)
    with editing(folder) as record:
        # Only what the previous publication published is replaced: files written in place stay.
        for name in set(record.get("published", [])) - set(files):
            (folder / name).unlink(missing_ok=True)
            record["files"].pop(name, None)
        record["files"].update({name: file_sha256(folder / name) for name in files if (folder / name).is_file()})
        record["files"] = {name: sha for name, sha in record["files"].items() if (folder / name).is_file()}
        for method in methods:
            drop_earlier_run_files(folder, record, method, files)
        record["published"] = files
        record["methods"] = {
            method: {**binding, "files": method_files(files, method)} for method, binding in methods.items()
        }
        record["run_id"] = record["next"]["run_id"]
        record["state"] = "published"
        record["published_at"] = now()
        for key in ("stage", "next"):
            record.pop(key, None)
    shutil.rmtree(stage, ignore_errors=True)
    return files


def finish_publishing(folder: Path) -> bool:
    """Finish the publication a killed run left half done (called with the folder's lock held)."""
    record = read_record(folder)
    if record is None or record.get("state") != "publishing":
        return False
    stage = folder / str(record.get("stage"))
    if not stage.is_dir():
        stage.mkdir()  # every file was moved already: only the record is left to write
    _move_and_record(folder, stage)
    return True


def changed_files(folder: str | os.PathLike[str], names: Iterable[str] | None = None) -> list[str]:
    """Of the recorded files (or ``names`` among them), those changed or gone since written."""
    folder = Path(folder)
    record = read_record(folder) or {"files": {}}
    listed = record["files"]
    wanted = listed if names is None else [n for n in names if n in listed]
    return [n for n in wanted if not (folder / n).is_file() or file_sha256(folder / n) != listed[n]]


def _publications(folders: list[Path]) -> list[tuple[Any, ...] | None]:
    records = [read_record(folder) for folder in folders]
    return [None if r is None else (r.get("state"), r.get("run_id"), r.get("published_at")) for r in records]


def read_whole(folders: str | os.PathLike[str] | Iterable[str | os.PathLike[str]], read: Callable[[], T]) -> T:
    """``read()`` of one whole publication of each folder: a publishing run is waited for, and a
    read it overlapped starts again, so a reader never sees half of two runs."""
    import time

    paths = [Path(folders)] if isinstance(folders, (str, os.PathLike)) else [Path(f) for f in folders]
    deadline = time.monotonic() + READ_WAIT_SECONDS
    while True:
        before = _publications(paths)
        moving = any(p and p[0] == "publishing" and running(f) is not None for f, p in zip(paths, before))
        if moving and time.monotonic() < deadline:
            time.sleep(0.02)
            continue
        try:
            result = read()
        except GVBenchError:
            if _publications(paths) != before and time.monotonic() < deadline:
                continue  # refused what a publication left mid-way: read the new one
            raise
        if _publications(paths) == before:
            return result
        if time.monotonic() >= deadline:
            raise RecordError(
                f"{', '.join(map(str, paths))} kept being published into for {READ_WAIT_SECONDS} s while it was "
                "read; read it once the runs writing it have finished"
            )


def check_published(folder: str | os.PathLike[str]) -> dict[str, Any]:
    """The record of a folder whose results a reader may use; ``RecordError`` otherwise."""
    folder = Path(folder)
    record = read_record(folder)
    if record is None:
        raise RecordError(
            f"{folder} holds no {RECORD_NAME}, so no gvbench-nb run wrote it (or it was written by an older "
            "version); run the methods into a new folder (python -m gvbench_nb run PARAMS --output-dir NEW)"
        )
    if record.get("state") == "publishing" and running(folder) is None:
        # A run killed while publishing: finish its move (when that fails, it is refused below).
        with contextlib.suppress(RecordError, OSError), FolderLock(folder):
            finish_publishing(folder)
        record = read_record(folder) or record
    holder = running(folder) if record.get("state") == "publishing" else None
    if holder is not None:
        raise RecordError(
            f"a run (pid {holder.get('pid')}) is publishing its results into {folder} now; read it again in a moment"
        )
    if record.get("state") == "publishing":
        raise RecordError(
            f"{folder}: a run stopped while publishing its results ({record.get('stage')}); run it again "
            "(python -m gvbench_nb run PARAMS) to finish"
        )
    return record
