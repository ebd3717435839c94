"""An output folder's runs. Every door that produces results (``run``, a stage notebook, a shard, a
merge, an import) adds ``runs/<id>/``: built aside in ``runs/.building-<id>`` and made visible by one
rename, never changed or deleted afterwards, so two writers never share a file. What users read at
the folder's top (``results.csv``) is derived from the runs by one rule (``current``) and can always
be made again; an earlier run is read by its id (``results OUT --run ID``).

The rule: the folder's current pairs and labels are those of its latest run; its current images and
recipe (profile, seed, verifier overrides) those of the latest computed run on those pairs. A
method's current run is its latest run, shown when it is of those inputs (an imported run read no
images and follows no recipe: its pairs and labels bind it); every other method is left out, named.
"""

from __future__ import annotations

import contextlib
import datetime as _dt
import json
import os
import secrets
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any, NamedTuple

from gvbench_nb import GVBenchError, __version__
from gvbench_nb import methods as method_registry
from gvbench_nb.io_utils import atomic_write_json, fsync_folder

RUNS = "runs"
BUILDING = ".building-"
MANIFEST = "manifest.json"  # in a run: its id, door, methods and when it was made visible
OLD_RECORD = "gvbench-run.json"  # what folders written before runs held at their top
PACKAGE = "gvbench-nb"


class RunsError(GVBenchError, ValueError):
    """An output folder is not the package's, or a run asked for is not in it."""


class Entry(NamedTuple):
    """One method's results in one run."""

    run: Path  # the run's folder
    method: str
    record: dict[str, Any]  # the method's run.json

    @property
    def folder(self) -> Path:
        return self.run / self.method


class View(NamedTuple):
    """What a folder shows: each method's current run, and the runs left out with why."""

    entries: dict[str, Entry]
    left_out: dict[str, str]  # method -> why its latest run is not shown (and how to show it)


def now() -> str:
    return _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")


def is_run(folder: str | os.PathLike[str]) -> bool:
    """Whether ``folder`` is one run (finished or being built), not an output folder."""
    return Path(folder).parent.name == RUNS


def run_id(folder: str | os.PathLike[str]) -> str | None:
    """The id of a run's folder (also while it is built), else None."""
    name = Path(folder).name
    return name.removeprefix(BUILDING) if is_run(folder) else None


def output_folder(folder: str | os.PathLike[str]) -> Path:
    """The output folder of a run's folder; an output folder itself."""
    return Path(folder).parent.parent if is_run(folder) else Path(folder)


def check_owned(output_dir: str | os.PathLike[str]) -> None:
    """Refuse, in one sentence, a folder that is neither missing, empty nor the package's."""
    folder = Path(output_dir)
    if not folder.is_dir() or is_run(folder) or (folder / RUNS).is_dir():
        return
    if (folder / OLD_RECORD).is_file():
        raise RunsError(
            f"{folder} holds results in the layout of an earlier gvbench-nb (its {OLD_RECORD}); take them in as "
            f"runs with `python -m gvbench_nb upgrade {folder}` (nothing is deleted), or give another output_dir"
        )
    entries = sorted(p.name for p in folder.iterdir())
    if entries:
        shown = ", ".join(entries[:3]) + (f" and {len(entries) - 3} more" if len(entries) > 3 else "")
        raise RunsError(
            f"output folder {folder} is not empty ({shown}) and holds no {RUNS}/ folder, so it is not gvbench-nb's to "
            "write in; give a new or empty output_dir (or --output-dir), or the folder of an earlier run"
        )


def claim(output_dir: str | os.PathLike[str]) -> None:
    """Make ``output_dir`` the package's (its ``runs/``) before a writer that adds no run yet writes
    there (a notebook's figures, a Dask run's match stores), so that the next door takes it."""
    check_owned(output_dir)
    if not is_run(output_dir):
        (Path(output_dir) / RUNS).mkdir(parents=True, exist_ok=True)


def _new_id(door: str) -> str:
    stamp = _dt.datetime.now(_dt.timezone.utc).strftime("%Y%m%dT%H%M%S")
    return f"{stamp}-{door}-{secrets.token_hex(3)}"


def start(output_dir: str | os.PathLike[str], door: str) -> Path:
    """A new run's folder, built aside (``runs/.building-<id>``) until ``finish`` makes it visible."""
    check_owned(output_dir)
    if is_run(output_dir):  # a finished run never changes
        raise RunsError(
            f"{output_dir} is a run of the output folder {output_folder(output_dir)}, and a run never changes; "
            "give that output folder as output_dir"
        )
    return _building(Path(output_dir), door)


def _building(output_dir: Path, door: str) -> Path:
    folder = output_dir / RUNS / f"{BUILDING}{_new_id(door)}"
    folder.mkdir(parents=True)
    atomic_write_json(folder / MANIFEST, {"package": PACKAGE, "door": door, "started_at": now()})
    return folder


def finish(building: Path, **details: Any) -> Path:
    """Make a built run visible by one rename; its manifest names its methods and when."""
    manifest = json.loads((building / MANIFEST).read_text(encoding="utf-8"))
    final = building.with_name(building.name.removeprefix(BUILDING))
    manifest.update(
        run_id=final.name,
        version=__version__,
        methods=sorted(p.parent.name for p in building.glob("*/pairs.csv")),
        command=" ".join(sys.argv),
        finished_at=now(),
        finished_ns=time.time_ns(),
        **details,
    )
    atomic_write_json(building / MANIFEST, manifest)
    fsync_folder(building)
    os.rename(building, final)
    fsync_folder(final.parent)
    return final


@contextlib.contextmanager
def new_run(output_dir: str | os.PathLike[str], door: str) -> Iterator[Path]:
    """A run built in the block and made visible when it ends without error (else left aside, named)."""
    building = start(output_dir, door)
    yield building
    finish(building)


_read: dict[tuple[str, int, int], Any] = {}  # a file's JSON by path, mtime and size: views read each run once


def _json(path: Path) -> Any:
    """A run's JSON file, read once a process unless it changed (a finished run does not); None when unreadable."""
    try:
        stat = path.stat()
        key = (str(path), stat.st_mtime_ns, stat.st_size)
        if key not in _read:
            _read[key] = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    return _read[key]


def _manifest(folder: Path) -> dict[str, Any] | None:
    manifest = _json(folder / MANIFEST)
    return manifest if isinstance(manifest, dict) and "finished_ns" in manifest else None


def finished_runs(output_dir: str | os.PathLike[str]) -> list[tuple[Path, dict[str, Any]]]:
    """The folder's finished runs with their manifests, oldest first."""
    root = Path(output_dir) / RUNS
    found = []
    for folder in root.iterdir() if root.is_dir() else []:
        manifest = None if folder.name.startswith(".") else _manifest(folder)
        if manifest is not None:
            found.append((folder, manifest))
    return sorted(found, key=lambda item: (item[1]["finished_ns"], item[0].name))


def find_run(output_dir: str | os.PathLike[str], wanted: str) -> Path:
    """The finished run ``wanted`` (an id, or its unique beginning) of ``output_dir``."""
    runs = [folder for folder, _ in finished_runs(output_dir)]
    matching = [folder for folder in runs if folder.name == wanted] or [f for f in runs if f.name.startswith(wanted)]
    if len(matching) != 1:
        known = ", ".join(f.name for f in runs[-5:]) or "none"
        what = "matches several runs" if matching else "is not a run"
        raise RunsError(f"{wanted!r} {what} of {output_dir} (latest: {known}); give one of its runs' ids")
    return matching[0]


def entries(output_dir: str | os.PathLike[str]) -> list[Entry]:
    """Every method's results in every finished run, oldest first (shards' partial work left out)."""
    found = []
    for folder, manifest in finished_runs(output_dir):
        if manifest.get("door") == "shard":
            continue
        for method in manifest.get("methods", []):
            record = _json(folder / method / "run.json")
            if isinstance(record, dict):
                found.append(Entry(folder, method, record))
    return found


def recipe(record: dict[str, Any]) -> dict[str, Any] | None:
    """What one table's rows share: profile, seed and the verifier settings the params changed
    (None for imported scores, which follow no recipe here)."""
    conf = record.get("conf") or {}
    if "imported" in record:
        return None
    try:
        default = method_registry.resolve_method(conf["method"], conf["profile"], None)["verifier"] or {}
    except Exception:  # a method this version does not know: its whole verifier is its recipe
        default = {}
    verifier = conf.get("verifier") or {}
    changed = {
        key: verifier.get(key) for key in sorted(set(verifier) | set(default)) if verifier.get(key) != default.get(key)
    }
    return json.loads(
        json.dumps({"profile": conf.get("profile"), "seed": record.get("seed"), "verifier": changed}, default=str)
    )


def _inputs(record: dict[str, Any]) -> tuple[Any, Any]:
    binding = record.get("binding") or {}
    return binding.get("pairs_digest"), binding.get("images_digest")


def current(output_dir: str | os.PathLike[str]) -> View:
    """Each method's current run by the module's rule, and the methods left out with why."""
    found = entries(output_dir)
    if not found:
        return View({}, {})
    described = [(entry, *_inputs(entry.record), recipe(entry.record)) for entry in found]
    pairs = described[-1][1]
    computed = [d for d in described if d[1] == pairs and d[3] is not None]
    images, wanted = (computed[-1][2], computed[-1][3]) if computed else (None, None)
    latest = {d[0].method: d for d in described}  # a method's latest run
    shown, left_out = {}, {}
    for method, (entry, entry_pairs, entry_images, entry_recipe) in latest.items():
        if entry_pairs != pairs:
            why = f"scored {entry.record.get('n_pairs')} other pairs or labels"
        elif entry_recipe is not None and (entry_images, entry_recipe) != (images, wanted):
            why = "read other images" if entry_images != images else f"ran under another recipe ({entry_recipe})"
        else:
            shown[method] = entry
            continue
        left_out[method] = (
            f"{method}: its latest run {entry.run.name} {why} (results {output_dir} --run {entry.run.name})"
        )
    order = {name: rank for rank, name in enumerate(method_registry.method_names())}
    ordered = dict(sorted(shown.items(), key=lambda item: (order.get(item[0], len(order)), item[0])))
    return View(ordered, left_out)


def method_folder(output_dir: str | os.PathLike[str], method: str) -> Path:
    """Where a method's results are read: in a run, its own folder; in an output folder, its
    current run's (``output_dir/method``, which does not exist, when it has none)."""
    folder = Path(output_dir)
    if is_run(folder):
        return folder / method
    entry = current(folder).entries.get(method)
    return entry.folder if entry is not None else folder / method


def upgrade(output_dir: str | os.PathLike[str]) -> Path:
    """Take the results of a folder written before runs in as one run (copies; nothing deleted)."""
    import shutil

    folder = Path(output_dir)
    methods = sorted(p.parent.name for p in folder.glob("*/pairs.csv") if (p.parent / "run.json").is_file())
    if not (folder / OLD_RECORD).is_file() or (folder / RUNS).is_dir():
        raise RunsError(
            f"{folder} holds no results of an earlier layout ({OLD_RECORD} without {RUNS}/); nothing to upgrade"
        )
    building = _building(folder, "upgrade")  # not ``start``: it refuses a folder of the earlier layout
    for method in methods:
        (building / method).mkdir()
        for name in ("run.json", "pairs.csv"):
            shutil.copy2(folder / method / name, building / method / name)
    return finish(building, upgraded_from=str(folder / OLD_RECORD))


def resolved_params(output_dir: str | os.PathLike[str]) -> Path | None:
    """The params file (``params.resolved.yaml``) of the latest run the folder shows (or of this run), else None."""
    from gvbench_nb.runner.config import RESOLVED_PARAMS_NAME as name

    if is_run(output_dir):
        return Path(output_dir) / name if (Path(output_dir) / name).is_file() else None
    shown = sorted(
        {e.run for e in current(output_dir).entries.values()},
        key=lambda run: (_manifest(run) or {}).get("finished_ns", 0),
    )
    return next((run / name for run in reversed(shown) if (run / name).is_file()), None)
