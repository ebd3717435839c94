"""Datasets a user can get: ``python -m gvbench_nb data fetch|list|check``.

The datasets and the SHA-256 of every file live in ``datasets.json`` beside this module.
A fetch writes each file to a hidden partial file beside its target (resumed with an HTTP
Range request after a cut connection), checks its size and hash, then renames it into
place, so a file under its final name is always complete and verified. Only the standard
library (and tqdm, lazily) is imported here: ``data`` runs without torch.
"""

from __future__ import annotations

import contextlib
import hashlib
import http.client
import json
import os
import shutil
import sys
import urllib.error
import urllib.parse
import urllib.request
from collections.abc import Iterable
from collections.abc import Sequence as SequenceType
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from gvbench_nb import GVBenchError
from gvbench_nb.protocol import registry

MANIFEST_PATH = Path(__file__).resolve().parent / "datasets.json"
APP_NAME = "gvbench-nb"
CHUNK_BYTES = 1 << 16
TIMEOUT_SECONDS = 60.0
ATTEMPTS = 4  # a cut connection is resumed this many times before the fetch gives up


class DataError(GVBenchError, RuntimeError):
    """A dataset cannot be fetched or checked; the message says which file, where and what to do."""


def data_dir() -> Path:
    """The data folder: ``$GVBENCH_DATA``, else a per-user cache folder (``data`` in platformdirs' cache)."""
    value = os.environ.get("GVBENCH_DATA")
    if value:
        return Path(value).expanduser().resolve()
    import platformdirs

    return platformdirs.user_cache_path(APP_NAME) / "data"


@dataclass(frozen=True)
class DataFile:
    path: str  # relative to the dataset's folder (and so to a mirror's folder of the same name)
    source: str  # relative to the dataset's base_url
    bytes: int | None  # None: not known beforehand (a checkpoint), so a cut download starts again
    sha256: str


@dataclass(frozen=True)
class Dataset:
    name: str
    folder: str  # under the data folder
    title: str
    what: str
    licence: str
    citation: str
    homepage: str
    base_url: str
    files: tuple[DataFile, ...]

    @property
    def total_bytes(self) -> int:
        return sum(f.bytes or 0 for f in self.files)

    def url(self, item: DataFile) -> str:
        return self.base_url + urllib.parse.quote(item.source)


@dataclass(frozen=True)
class ExternalDataset:
    """A dataset without stable per-file URLs: where to get it and how to lay it out."""

    name: str
    title: str
    what: str
    licence: str
    citation: str
    where: str
    layout: str
    check: str


def load_manifest(path: Path = MANIFEST_PATH) -> tuple[dict[str, Dataset], dict[str, ExternalDataset]]:
    """The fetchable datasets and the external ones, by name."""
    raw = json.loads(path.read_text(encoding="utf-8"))
    datasets = {
        name: Dataset(name=name, files=tuple(DataFile(**f) for f in entry.pop("files")), **entry)
        for name, entry in raw["datasets"].items()
    }
    external = {name: ExternalDataset(name=name, **entry) for name, entry in raw["external"].items()}
    return datasets, external


def get_dataset(name: str, datasets: dict[str, Dataset] | None = None) -> Dataset:
    datasets = datasets if datasets is not None else load_manifest()[0]
    if name not in datasets:
        _, external = load_manifest()
        if name in external:
            raise DataError(
                f"{name} cannot be fetched (no stable per-file URLs): get it from {external[name].where} "
                f"and check it with `{external[name].check}`"
            )
        raise DataError(
            registry.unknown_name_message("dataset", name, datasets)
            + " (python -m gvbench_nb data list describes them)"
        )
    return datasets[name]


def sha256_of(path: Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as handle:
        for block in iter(lambda: handle.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def is_verified(path: Path, item: DataFile) -> bool:
    """The file exists with the manifest's size and SHA-256."""
    return path.is_file() and path.stat().st_size == item.bytes and sha256_of(path) == item.sha256


def partial_path(target: Path) -> Path:
    """Where a file is written while it arrives: hidden, beside its final name."""
    return target.with_name(f".{target.name}.partial")


def presence(dataset: Dataset, root: Path) -> tuple[int, int]:
    """(files present with the right size, files in the manifest) under ``root``; no hashing."""
    folder = root / dataset.folder
    found = sum(1 for f in dataset.files if (folder / f.path).is_file() and (folder / f.path).stat().st_size == f.bytes)
    return found, len(dataset.files)


# ------------------------------------------------------------------- fetching --
def _is_url(text: str) -> bool:
    return urllib.parse.urlparse(text).scheme in {"http", "https", "file"}


def _source_of(dataset: Dataset, item: DataFile, mirror: str | None) -> tuple[str, Path | None]:
    """(URL or path shown to the user, local path when the mirror is a folder)."""
    if mirror is None:
        return dataset.url(item), None
    if _is_url(mirror):
        return mirror.rstrip("/") + "/" + urllib.parse.quote(f"{dataset.folder}/{item.path}"), None
    local = Path(mirror).expanduser().resolve() / dataset.folder / item.path
    return str(local), local


def _download(url: str, partial: Path, item: DataFile, label: str, bar: Any, folder: str = "") -> None:
    """Bring ``url`` into ``partial``, resuming from what it holds; raise DataError when it cannot.
    ``folder``: the dataset's folder in the data folder, which a --mirror copy must hold."""
    last_problem = ""
    connected = False  # whether any attempt reached the source: offline, rerunning cannot help
    for _ in range(ATTEMPTS):
        have = partial.stat().st_size if partial.is_file() else 0
        if have and (item.bytes is None or have > item.bytes):  # not a prefix of the file: start again
            partial.unlink()
            bar.update(-have)
            have = 0
        if have == item.bytes:
            return
        headers = {"User-Agent": f"{APP_NAME} data fetch"}
        if have:
            headers["Range"] = f"bytes={have}-"
        try:
            with urllib.request.urlopen(urllib.request.Request(url, headers=headers), timeout=TIMEOUT_SECONDS) as reply:
                connected = True
                if have and getattr(reply, "status", 200) != 206:  # the server ignored the range: start again
                    bar.update(-have)
                    have = 0
                with open(partial, "ab" if have else "wb") as out:
                    for block in iter(lambda: reply.read(CHUNK_BYTES), b""):
                        out.write(block)
                        bar.update(len(block))
                    out.flush()
                    os.fsync(out.fileno())
        except urllib.error.HTTPError as error:
            if error.code == 416 and have:  # the range starts past the end: what we hold is stale
                partial.unlink()
                bar.update(-have)
                continue
            raise DataError(
                f"{label}: {url} answered HTTP {error.code} {error.reason}; check the address (or that the "
                f"source still has the file), or pass --mirror with a folder or URL holding the same layout"
            ) from None
        except PermissionError:
            raise  # the data folder is not writable: no retry helps (fetch says what to do)
        except (urllib.error.URLError, http.client.HTTPException, OSError) as error:
            last_problem = str(getattr(error, "reason", None) or error) or type(error).__name__
            continue  # a cut connection: resume from what arrived
        if partial.is_file() and partial.stat().st_size >= (item.bytes or 0):
            return
        last_problem = "the connection closed early"
    kept = partial.stat().st_size if partial.is_file() else 0
    if not connected:
        host = urllib.parse.urlsplit(url).netloc or url
        earlier = (
            f"the {kept} bytes an earlier attempt left in {partial} are kept for when it is"
            if kept
            else "nothing was downloaded"
        )
        raise DataError(
            f"{label}: cannot reach {host} ({last_problem}): the network or the source is unreachable and "
            f"{earlier}; pass --mirror DIR with a local copy of the data folder (one holding {folder}/), "
            "or run the same command again once the source is reachable"
        )
    raise DataError(
        f"{label}: could not download {url} after {ATTEMPTS} attempts ({last_problem}); {kept} of {item.bytes} "
        f"bytes are kept in {partial}: rerun the same command to resume, or pass --mirror with a local copy"
    )


def fetch_file(dataset: Dataset, item: DataFile, root: Path, mirror: str | None, bar: Any) -> bool:
    """Place one verified file under ``root``; False when it was already there and verified."""
    target = root / dataset.folder / item.path
    if is_verified(target, item):
        bar.update(item.bytes)
        return False
    target.parent.mkdir(parents=True, exist_ok=True)
    partial = partial_path(target)
    source, local = _source_of(dataset, item, mirror)
    if local is not None:
        if not local.is_file():
            raise DataError(
                f"{dataset.name}: {item.path} is missing in the mirror folder (expected {local}); "
                f"pass --mirror a folder holding {dataset.folder}/ with the files of `data fetch`, "
                "or omit --mirror to download from the public source"
            )
        shutil.copyfile(local, partial)
        bar.update(item.bytes)
    else:
        bar.update(partial.stat().st_size if partial.is_file() else 0)
        _download(source, partial, item, f"{dataset.name}: {item.path}", bar, dataset.folder)
    size = partial.stat().st_size
    digest = sha256_of(partial)
    if size != item.bytes or digest != item.sha256:
        partial.unlink()
        raise DataError(
            f"{dataset.name}: {item.path} from {source} has {size} bytes and SHA-256 {digest}, but the manifest "
            f"says {item.bytes} bytes and {item.sha256}; the copy was removed: rerun to download it again, and if "
            "it fails again the source has changed (use --mirror with a copy that matches)"
        )
    os.replace(partial, target)  # atomic: the final name only ever holds a verified file
    return True


def fetch(
    names: Iterable[str],
    to: Path | None = None,
    mirror: str | None = None,
    progress: bool = True,
    datasets: dict[str, Dataset] | None = None,
) -> dict[str, int]:
    """Fetch datasets (default: the package manifest's) into ``to`` (default: :func:`data_dir`);
    returns how many files each dataset placed now (0: all were there and verified)."""
    from gvbench_nb.io_utils import progress_bar

    datasets = datasets if datasets is not None else load_manifest()[0]
    chosen = [get_dataset(name, datasets) for name in dict.fromkeys(names)]
    root = Path(to).expanduser().resolve() if to is not None else data_dir()
    root_existed = root.is_dir()
    try:
        root.mkdir(parents=True, exist_ok=True)
    except OSError as error:
        raise DataError(
            f"cannot create the data folder {root} ({error.strerror}); set GVBENCH_DATA or pass --to a writable folder"
        ) from None
    placed: dict[str, int] = {}
    for dataset in chosen:
        count = 0
        folders_before = _folders_under(root / dataset.folder)
        with progress_bar(
            total=dataset.total_bytes,
            unit="B",
            unit_scale=True,
            unit_divisor=1024,
            desc=dataset.name,
            disable=not progress,
            file=sys.stderr,
            leave=True,
        ) as bar:
            try:
                for item in dataset.files:
                    try:
                        count += fetch_file(dataset, item, root, mirror, bar)
                    except PermissionError as error:
                        raise DataError(
                            f"{dataset.name}: cannot write {error.filename} (permission denied); "
                            "set GVBENCH_DATA or pass --to a writable folder"
                        ) from None
            except BaseException:
                _remove_empty_folders(root / dataset.folder, folders_before)
                if not root_existed:
                    with contextlib.suppress(OSError):  # holds other datasets' files: stays
                        root.rmdir()
                raise
        placed[dataset.name] = count
    return placed


def _folders_under(folder: Path) -> set[Path]:
    """``folder`` and every folder below it that exists now."""
    if not folder.is_dir():
        return set()
    return {folder, *(p for p in folder.rglob("*") if p.is_dir())}


def _remove_empty_folders(folder: Path, keep: set[Path]) -> None:
    """Remove the folders a failed fetch created and left empty (deepest first); ``keep`` were there before."""
    for path in sorted(_folders_under(folder) - keep, key=lambda p: len(p.parts), reverse=True):
        with contextlib.suppress(OSError):  # not empty: it holds files placed now, which stay
            path.rmdir()


# ------------------------------------------------------------------- checking --
@dataclass
class ImageCheck:
    named: int
    present: int
    decoded: int
    missing: list[str]
    undecodable: list[str]

    @property
    def ok(self) -> bool:
        return self.named > 0 and not self.missing and not self.undecodable


def check_images(root: Path, names: SequenceType[str], progress: bool = True) -> ImageCheck:
    """Every named image exists under ``root`` and decodes (OpenCV)."""
    import cv2

    from gvbench_nb.io_utils import progress_bar

    missing, undecodable = [], []
    present = 0
    for name in progress_bar(names, desc="images", unit="img", disable=not progress, file=sys.stderr):
        path = root / name
        if not path.is_file():
            missing.append(name)
            continue
        present += 1
        if cv2.imread(str(path), cv2.IMREAD_UNCHANGED) is None:
            undecodable.append(name)
    return ImageCheck(len(names), present, present - len(undecodable), missing, undecodable)


def _builder_folders(options: dict[str, Any]) -> list[str]:
    folders = [options.get("query_folder"), options.get("reference_folder"), *(options.get("reference_folders") or [])]
    return [f for f in folders if f]


def images_of_params(params: dict[str, Any]) -> tuple[list[str], str, list[str]]:
    """The images a sequence names (relative to its image root), where the names came from
    (a builder's folders when it has them: its pair file is made from them; else the pair
    list) and the builder's folders that do not exist (they name no image)."""
    from gvbench_nb.protocol.images import IMAGE_EXTENSIONS

    folders = _builder_folders(dict(params["builder_options"]))
    if params["pairs_builder"] and folders:
        root = Path(params["image_root"])
        names: list[str] = []
        missing_folders = []
        for folder in folders:
            directory = root / folder
            if not directory.is_dir():
                missing_folders.append(f"{folder}/")
                continue
            names += sorted(f"{folder}/{p.name}" for p in directory.iterdir() if p.suffix.lower() in IMAGE_EXTENSIONS)
        return (
            names,
            f"the folders {', '.join(folders)} (the {params['pairs_builder']} builder makes the pairs from them)",
            missing_folders,
        )
    pairs = Path(params["pairs"])
    if pairs.is_file():
        from gvbench_nb.data.sequences import read_pairs

        found = read_pairs(pairs)
        return list(dict.fromkeys(n for p in found for n in (p.query, p.reference))), f"the pair list {pairs}", []
    raise DataError(
        f"{params['params_file']}: its pair list {pairs} does not exist; for an official sequence run "
        "`python -m gvbench_nb data fetch gvbench-lists` (or set GVBENCH_DATA to the folder holding gvbench_gt/)"
    )


def fetch_hint(folder: Path) -> str:
    """`data fetch NAME` when ``folder`` is (inside) a dataset's place in the data folder, else ''."""
    datasets, _ = load_manifest()
    root = data_dir()
    for dataset in datasets.values():
        place = root / dataset.folder
        if folder == place or place in folder.parents:
            return f"; run `python -m gvbench_nb data fetch {dataset.name}`"
    return ""


# -------------------------------------------------------------------- listing --
def _size(n: int) -> str:
    size = float(n)
    for unit in ("B", "KiB", "MiB", "GiB"):
        if size < 1024 or unit == "GiB":
            return f"{size:.0f} {unit}" if unit == "B" else f"{size:.1f} {unit}"
        size /= 1024
    return str(size)


def list_text(root: Path | None = None) -> str:
    datasets, external = load_manifest()
    root = root if root is not None else data_dir()
    lines = [f"data folder: {root}  (GVBENCH_DATA, else the per-user cache)", ""]
    for d in datasets.values():
        found, total = presence(d, root)
        state = "present" if found == total else ("absent" if found == 0 else f"partial ({found}/{total} files)")
        lines += [
            f"{d.name}  ({d.title}; {total} files, {_size(d.total_bytes)}; {state} in {root / d.folder})",
            f"  what:     {d.what}",
            f"  licence:  {d.licence}",
            f"  cite:     {d.citation}",
            f"  source:   {d.homepage}",
            f"  get it:   python -m gvbench_nb data fetch {d.name}",
            "",
        ]
    for e in external.values():
        lines += [
            f"{e.name}  ({e.title}; not fetchable: no stable per-file URLs)",
            f"  what:     {e.what}",
            f"  licence:  {e.licence}",
            f"  cite:     {e.citation}",
            f"  get it:   {e.where}",
            f"  layout:   {e.layout}",
            f"  check:    {e.check}",
            "",
        ]
    return "\n".join(lines).rstrip() + "\n"


def check_params(params: dict[str, Any], progress: bool = True) -> tuple[bool, str]:
    """Check the images a loaded params file's sequence names; returns whether all are usable, and a report."""
    from gvbench_nb.data.sequences import PairFileError

    params_file = params["params_file"]
    if params["pairs_builder"] == "sample":
        return True, f"{params['sequence']}: its images are rendered by the run (builder sample); nothing to check"
    if params["image_root"] is None:
        raise DataError(
            f"{params_file}: image_root is not set; pass --image-root DIR, the folder the pair paths are relative to "
            "(for the official sequences the one holding day0/, night0/, season1/, ...; see `python -m gvbench_nb data list`)"
        )
    root = Path(params["image_root"])
    try:
        names, origin, missing_folders = images_of_params(params)
    except PairFileError as error:
        raise DataError(str(error)) from None
    result = check_images(root, names, progress=progress)
    lines = [
        f"{params['sequence']}: {result.named} images named by {origin}, under {root}",
        f"  present {result.present}, decode {result.decoded}, missing {len(result.missing)}, "
        f"do not decode {len(result.undecodable)}",
    ]
    if missing_folders:
        lines.append(f"  missing folders: {', '.join(missing_folders)}{fetch_hint(root)}")
    if result.missing:
        official = Path(params["pairs"]).parent == data_dir() / get_dataset("gvbench-lists").folder
        hint = (
            (
                "; the GV-Bench images are not fetchable: `python -m gvbench_nb data list` says where to get them "
                "(gvbench-images) and how to lay them out"
            )
            if official
            else fetch_hint(root)
        )
        lines.append("  first missing: " + ", ".join(result.missing[:10]) + hint)
    if result.undecodable:
        lines.append("  first that do not decode: " + ", ".join(result.undecodable[:10]))
    if result.named == 0 and not missing_folders:
        lines.append(f"  no images found: check image_root ({root}){fetch_hint(root)}")
    ok = result.ok and not missing_folders
    lines.append("  ok" if ok else "  NOT ready to run")
    return ok, "\n".join(lines)
