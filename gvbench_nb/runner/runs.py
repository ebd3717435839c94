"""An output folder's runs. Every door that produces results (``run``, a stage notebook, a shard, a
merge, an import) adds ``runs/<id>/``: built aside in ``runs/.building-<id>`` and made visible by one
rename, never changed or deleted afterwards, so two writers never share a file. ``finish`` seals a
run: its manifest lists every file with its size and BLAKE2b, and carries the hash of its own content;
every read of a run goes through that list (``sealed``), so an edited, missing or extra file, or a
damaged manifest, is refused naming the run and the file, never read nor passed over. What users read
at the folder's top (``results.csv``) is written for people from the runs by one rule (``current``) and
never read back; an earlier run is read by its id (``results OUT --run ID``).

The rule: the folder's current pairs and labels are those of its latest run; its current images those
of the latest computed run on those pairs. Each method shows, under each recipe it ran (profile, seed,
verifier overrides), its latest run under that recipe, when it is of those inputs; an imported run
(which read no images and follows no recipe: its pairs and labels bind it) replaces the method's
earlier runs. A method shown under several recipes has a row each, labelled by what tells them apart
(``orb-nn (paper profile)``); every other run is left out, named.
"""

from __future__ import annotations

import contextlib
import datetime as _dt
import hashlib
import json
import os
import platform
import secrets
import shutil
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any, NamedTuple

from gvbench_nb import GVBenchError, __version__
from gvbench_nb import methods as method_registry
from gvbench_nb.io_utils import atomic_write_json, fsync_folder, hash_file

RUNS = "runs"
BUILDING = ".building-"
MANIFEST = "manifest.json"  # in a run: its id, door, methods, when it was made visible and its files' hashes
OLD_RECORD = "gvbench-run.json"  # what folders written before runs held at their top
PACKAGE = "gvbench-nb"


class RunsError(GVBenchError, ValueError):
    """An output folder is not the package's, or a run asked for is not in it."""


class Entry(NamedTuple):
    """One method's results in one run."""

    run: Path  # the run's folder
    method: str
    record: dict[str, Any]  # the method's run.json
    label: str = ""  # its row in a view: the method, or the method and what tells its recipes apart

    @property
    def folder(self) -> Path:
        return self.run / self.method

    @property
    def recipe(self) -> dict[str, Any] | None:
        return recipe(self.record)


class View(NamedTuple):
    """What a folder shows: a row (``Entry.label``) for each method under each recipe it ran on the
    current inputs, and the runs left out (row label -> why, and how to show it)."""

    entries: dict[str, Entry]
    left_out: dict[str, str]

    def of(self, method: str) -> list[Entry]:
        """The rows of ``method``, its latest run last."""
        rows = [entry for entry in self.entries.values() if entry.method == method]
        return sorted(rows, key=lambda entry: _finished_ns(entry.run))


def now() -> str:
    return _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")


def is_run(folder: str | os.PathLike[str]) -> bool:
    """Whether ``folder`` is one run (finished or being built), not an output folder."""
    return Path(folder).parent.name == RUNS


def run_id(folder: str | os.PathLike[str]) -> str | None:
    """The id of a run's folder (also while it is built), else None."""
    return Path(folder).name.removeprefix(BUILDING) if is_run(folder) else None


def output_folder(folder: str | os.PathLike[str]) -> Path:
    """The output folder of a run's folder; an output folder itself."""
    return Path(folder).parent.parent if is_run(folder) else Path(folder)


def check_owned(output_dir: str | os.PathLike[str]) -> None:
    """Refuse, in one sentence, a folder that is neither missing, empty nor the package's, or that
    holds a run that is not whole (named before anything reads or adds to the folder)."""
    folder = Path(output_dir)
    if not folder.is_dir() or is_run(folder):
        return
    if (folder / RUNS).is_dir():
        finished_runs(folder)
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
    stamp = _dt.datetime.now(_dt.timezone.utc).strftime("%Y%m%dT%H%M%S")
    folder = output_dir / RUNS / f"{BUILDING}{stamp}-{door}-{secrets.token_hex(3)}"
    folder.mkdir(parents=True)
    # Who builds it: ``clean`` removes a build only once that process has ended.
    builder = {"pid": os.getpid(), "host": platform.node()}
    atomic_write_json(folder / MANIFEST, {"package": PACKAGE, "door": door, "started_at": now(), **builder})
    return folder


# BLAKE2b by device, inode, size, mtime and ctime: a file hashed once a process
_digests: dict[tuple[int, ...], str] = {}


def _files(run: Path) -> dict[str, dict[str, Any]]:
    """Every file of a run but its manifest: relative path -> size and BLAKE2b."""
    found = {}
    for path in sorted(run.rglob("*")):
        name = path.relative_to(run).as_posix()
        if name == MANIFEST or path.is_dir():
            continue
        stat = path.stat()  # a rewrite in place changes ctime, which no tool sets back
        key = (stat.st_dev, stat.st_ino, stat.st_size, stat.st_mtime_ns, stat.st_ctime_ns)
        if key not in _digests:
            _digests[key] = hash_file(path, hashlib.blake2b())
        found[name] = {"size": stat.st_size, "blake2b": _digests[key]}
    return found


def _seal(manifest: dict[str, Any]) -> str:
    """The hash of a manifest's content (its file list included), kept in it: an edit or a cut shows."""
    content = json.dumps({k: v for k, v in manifest.items() if k != "seal"}, sort_keys=True, default=str)
    return hashlib.blake2b(content.encode()).hexdigest()


def finish(building: Path, **details: Any) -> Path:
    """Seal a built run (its manifest lists every file with its hash) and make it visible by one rename."""
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
    manifest = json.loads(json.dumps(manifest, default=str)) | {"files": _files(building)}
    atomic_write_json(building / MANIFEST, manifest | {"seal": _seal(manifest)})
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


def sealed(run: Path) -> dict[str, Any]:
    """A finished run's manifest, once every file of the run matched it (size and hash); otherwise
    ``RunsError`` naming the run, the file and what to do. Nothing of a run is read before this."""
    output_dir = run.parent.parent

    def refused(name: str, what: str) -> RunsError:
        return RunsError(
            f"run {run.name} of {output_dir}: its {name} {what}, so the run cannot be trusted; remove the folder "
            f"{run} (or restore it whole from a backup)"
        )

    if not run.is_dir():
        raise RunsError(f"{run} is not a run of {output_dir} (a run is a folder); move it out of {run.parent}")
    try:
        manifest = json.loads((run / MANIFEST).read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise refused(MANIFEST, "is missing") from None
    except (OSError, ValueError):
        raise refused(MANIFEST, "is damaged (not whole JSON)") from None
    if isinstance(manifest, dict) and "finished_ns" in manifest and "seal" not in manifest:
        raise RunsError(
            f"run {run.name} of {output_dir} was written before runs were sealed; seal the folder's runs as they "
            f"are with `python -m gvbench_nb upgrade {output_dir}`, or remove that run"
        )
    if not isinstance(manifest, dict) or manifest.get("seal") != _seal(manifest) or manifest.get("run_id") != run.name:
        raise refused(MANIFEST, "does not match its seal (edited or damaged)")
    listed, found = manifest["files"], _files(run)
    for name in sorted(set(listed) | set(found)):
        what = "is missing" if name not in found else "was added after the run finished" if name not in listed else ""
        if what or found[name] != listed[name]:
            raise refused(name, what or "changed after the run finished")
    _finished[run] = manifest["finished_ns"]
    return manifest


_finished: dict[Path, int] = {}  # a sealed run's finish time, as its manifest says
_records: dict[str, Any] = {}  # a run.json by its hash: a view parses each once a process


def finished_runs(output_dir: str | os.PathLike[str]) -> list[tuple[Path, dict[str, Any]]]:
    """The folder's finished runs with their manifests, oldest first, each checked whole (``sealed``)."""
    root = Path(output_dir) / RUNS
    found = [(run, sealed(run)) for run in (root.iterdir() if root.is_dir() else []) if not run.name.startswith(".")]
    return sorted(found, key=lambda item: (item[1]["finished_ns"], item[0].name))


def _finished_ns(run: Path) -> int:
    return _finished.get(run) or sealed(run)["finished_ns"]


def find_run(output_dir: str | os.PathLike[str], wanted: str) -> Path:
    """The finished run of ``output_dir`` whose id is ``wanted`` (the whole id), checked whole."""
    root = Path(output_dir) / RUNS
    if wanted and Path(wanted).name == wanted and not wanted.startswith(".") and (root / wanted).is_dir():
        sealed(root / wanted)  # the others need not be whole to read this one
        return root / wanted
    runs = [folder for folder, _ in finished_runs(output_dir)]
    beginning = [f.name for f in runs if wanted.strip() and f.name.startswith(wanted)]
    known = ", ".join(f.name for f in runs[-5:]) or "none"
    if not wanted.strip():
        raise RunsError(f"--run is empty (an unset variable?); give the whole id of one run of {output_dir}: {known}")
    if beginning:
        raise RunsError(
            f"{wanted!r} is not a run of {output_dir} but the beginning of {', '.join(beginning)}; give a whole id"
        )
    raise RunsError(f"{wanted!r} is not a run of {output_dir} (latest: {known}); give one of its runs' ids")


def entries(output_dir: str | os.PathLike[str]) -> list[Entry]:
    """Every method's results in every finished run, oldest first (shards' partial work left out)."""
    found = []
    for folder, manifest in finished_runs(output_dir):
        if manifest.get("door") == "shard":
            continue
        for method in manifest.get("methods", []):
            digest = manifest["files"].get(f"{method}/run.json", {}).get("blake2b")
            if digest is not None and digest not in _records:
                _records[digest] = json.loads((folder / method / "run.json").read_text(encoding="utf-8"))
            if isinstance(_records.get(digest), dict):
                found.append(Entry(folder, method, _records[digest], method))
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


def _labelled(rows: list[Entry]) -> dict[str, Entry]:
    """Each row under its label: its method, and, where the method has several rows, what tells their
    recipes apart (``orb-nn (paper profile)``, ``orb-nn (seed 1)``, ``orb-nn (threshold_px 8)``)."""
    labelled, recipes = {}, [entry.recipe or {} for entry in rows]
    for entry, mine in zip(rows, recipes):
        others = [theirs for other, theirs in zip(rows, recipes) if other.method == entry.method]
        words = {
            "profile": f"{mine.get('profile')} profile",
            "seed": f"seed {mine.get('seed')}",
            "verifier": ", ".join(f"{k} {v}" for k, v in (mine.get("verifier") or {}).items()) or "default verifier",
        }
        parts = [text for key, text in words.items() if len({json.dumps(o.get(key)) for o in others}) > 1]
        label = f"{entry.method} ({'; '.join(parts)})" if parts else entry.method
        labelled[label] = entry._replace(label=label)
    return labelled


def current(output_dir: str | os.PathLike[str]) -> View:
    """The folder's rows by the module's rule (keyed by label), and the runs left out with why."""
    found = entries(output_dir)
    if not found:
        return View({}, {})
    bindings = [entry.record.get("binding") or {} for entry in found]
    described = [(e, b.get("pairs_digest"), b.get("images_digest"), e.recipe) for e, b in zip(found, bindings)]
    pairs = described[-1][1]
    computed = [d for d in described if d[1] == pairs and d[3] is not None]
    images = computed[-1][2] if computed else None
    latest: dict[tuple[str, str], tuple[Entry, Any, Any, Any]] = {}  # (method, recipe) -> its latest run
    for d in described:
        method = d[0].method
        if d[3] is None or (method, "null") in latest:  # an import replaces the method's runs, and is replaced
            latest = {key: value for key, value in latest.items() if key[0] != method}
        latest[(method, json.dumps(d[3], sort_keys=True))] = d
    shown, left = [], []
    for entry, entry_pairs, entry_images, entry_recipe in latest.values():
        if entry_pairs != pairs:
            left.append((entry, f"scored {entry.record.get('n_pairs')} other pairs or labels"))
        elif entry_recipe is not None and entry_images != images:
            left.append((entry, "read other images"))
        else:
            shown.append(entry)
    named = {(e.run, e.method): label for label, e in _labelled([d[0] for d in latest.values()]).items()}
    left_out = {}
    for entry, why in left:
        label, run = named[entry.run, entry.method], entry.run.name
        left_out[label] = f"{label}: its latest run {run} {why} (results {output_dir} --run {run})"
    order = {name: rank for rank, name in enumerate(method_registry.method_names())}
    ordered = sorted(_labelled(shown).items(), key=lambda item: (order.get(item[1].method, len(order)), item[0]))
    return View(dict(ordered), left_out)


def method_folder(output_dir: str | os.PathLike[str], method: str) -> Path:
    """Where a method's results are read: in a run, its own folder (a finished run checked whole); in an
    output folder, its row's run (``method`` a row label, or a method: its latest row), else
    ``output_dir/method``, which does not exist."""
    folder = Path(output_dir)
    if is_run(folder):
        if not folder.name.startswith("."):
            sealed(folder)
        return folder / method
    entry = _row(folder, method)
    return entry.folder if entry is not None else folder / method


def _row(output_dir: Path, name: str) -> Entry | None:
    """The row an output folder shows under ``name``: a label, or a method (its latest row)."""
    view = current(output_dir)
    return view.entries.get(name) or next(reversed(view.of(name)), None)


def record(output_dir: str | os.PathLike[str], name: str) -> dict[str, Any] | None:
    """A method's ``run.json``: its row's in an output folder (``name`` a label, or a method: its latest
    row), its own in a run (a finished one checked whole first, a shard's or one being built as it is)."""
    folder = Path(output_dir)
    if not is_run(folder):
        entry = _row(folder, name)
        return entry.record if entry is not None else None
    path = method_folder(folder, name) / "run.json"
    return json.loads(path.read_text(encoding="utf-8")) if path.is_file() else None


def unfinished(output_dir: str | os.PathLike[str]) -> list[Path]:
    """The folder's runs being built, or left by a build that failed or was killed."""
    return sorted((Path(output_dir) / RUNS).glob(f"{BUILDING}*"))


ABANDONED_AFTER = 24 * 3600  # seconds unchanged after which a build of another machine is taken as abandoned


def abandoned(building: Path) -> bool:
    """Whether no process builds it any more: the one that started it (its manifest says which) has ended,
    or, started on another machine or by an earlier version, nothing in it changed for a day."""
    import psutil

    try:
        builder = json.loads((building / MANIFEST).read_text(encoding="utf-8"))
        started = _dt.datetime.fromisoformat(builder["started_at"]).timestamp()
        if builder.get("host") == platform.node():
            return psutil.Process(builder["pid"]).create_time() > started + 1  # its pid taken by another process
    except psutil.NoSuchProcess:
        return True
    except (OSError, ValueError, KeyError, TypeError, psutil.Error):
        pass
    changed = max((p.stat().st_mtime for p in [building, *building.rglob("*")]), default=0)
    return time.time() - changed > ABANDONED_AFTER


def _size(folder: Path) -> int:
    return sum(p.stat().st_size for p in folder.rglob("*") if p.is_file())


def leftovers(output_dir: str | os.PathLike[str]) -> str | None:
    """One line on the folder's unfinished builds (how many, how big, how many abandoned), else None."""
    builds = unfinished(output_dir)
    if not builds:
        return None
    size, gone = sum(map(_size, builds)), sum(map(abandoned, builds))
    return (
        f"{output_dir} holds {len(builds)} unfinished run{'s' if len(builds) > 1 else ''} ({RUNS}/{BUILDING}*, "
        f"{size / 1e6:.1f} MB), {gone} abandoned: `python -m gvbench_nb clean {output_dir}` removes those"
    )


def clean(output_dir: str | os.PathLike[str], superseded: bool = False) -> tuple[list[str], list[str]]:
    """Remove the folder's abandoned builds and, ``superseded``, the finished runs its view does not show;
    returns what was removed and the builds kept (still being built)."""
    builds = unfinished(output_dir)
    removed, kept = [b for b in builds if abandoned(b)], [b.name for b in builds if not abandoned(b)]
    if superseded:
        shown = {entry.run for entry in current(output_dir).entries.values()}
        for run, _ in finished_runs(output_dir):
            if run not in shown:  # out of every reader's sight by one rename, then deleted
                removed.append(run.rename(run.with_name(f"{BUILDING}removed-{run.name}")))
    for folder in removed:
        shutil.rmtree(folder)
    return [folder.name.removeprefix(f"{BUILDING}removed-") for folder in removed], kept


def upgrade(output_dir: str | os.PathLike[str]) -> str:
    """Take the results of a folder written before runs in as one run (copies; nothing deleted), or seal
    the runs written before runs were sealed, as they are; what was done, in a sentence."""
    folder = Path(output_dir)
    root = folder / RUNS
    unsealed = [run for run in (root.iterdir() if root.is_dir() else []) if _unsealed(run)]
    for run in unsealed:
        manifest = json.loads((run / MANIFEST).read_text(encoding="utf-8")) | {"files": _files(run)}
        atomic_write_json(run / MANIFEST, manifest | {"seal": _seal(manifest)})
    if unsealed:
        return f"{folder}: sealed {len(unsealed)} runs written before runs were sealed, as they are now"
    if not (folder / OLD_RECORD).is_file() or root.is_dir():
        raise RunsError(
            f"{folder} holds no results of an earlier layout ({OLD_RECORD} without {RUNS}/, or runs not sealed); "
            "nothing to upgrade"
        )
    try:
        record = json.loads((folder / OLD_RECORD).read_text(encoding="utf-8"))
    except ValueError:
        record = {}
    # A publication killed half way: its files are in its stage or already moved; the earlier version finished it.
    moving = record.get("next") if record.get("state") == "publishing" else None
    stage = folder / str(record.get("stage"))
    methods = sorted(moving["methods"]) if moving else sorted(p.parent.name for p in folder.glob("*/run.json"))
    building = _building(folder, "upgrade")  # not ``start``: it refuses a folder of the earlier layout
    for method in methods:
        (building / method).mkdir()
        for name in ("run.json", "pairs.csv"):
            source = stage / method / name if moving and (stage / method / name).is_file() else folder / method / name
            shutil.copy2(source, building / method / name)
    run = finish(
        building, upgraded_from=str(folder / OLD_RECORD), **({"finished_publication": stage.name} if moving else {})
    )
    finished = f", finishing the publication {stage.name} that was stopped half way" if moving else ""
    return f"{folder}: {', '.join(methods) or 'no results'} taken in as run {run.name}{finished}; its other files are as they were"


def _unsealed(run: Path) -> bool:
    with contextlib.suppress(OSError, ValueError, TypeError):
        manifest = json.loads((run / MANIFEST).read_text(encoding="utf-8"))
        return not run.name.startswith(".") and "finished_ns" in manifest and "seal" not in manifest
    return False


def resolved_params(output_dir: str | os.PathLike[str]) -> Path | None:
    """The params file (``params.resolved.yaml``) of the latest run the folder shows (or of this run), else None."""
    from gvbench_nb.runner.config import RESOLVED_PARAMS_NAME as name

    if is_run(output_dir):
        return Path(output_dir) / name if (Path(output_dir) / name).is_file() else None
    shown = sorted({e.run for e in current(output_dir).entries.values()}, key=_finished_ns)
    return next((run / name for run in reversed(shown) if (run / name).is_file()), None)
