"""Datasets a user can get: ``python -m gvbench_nb data fetch|list|check``. ``datasets.json`` beside
this module names every file and its SHA-256; pooch downloads each (trying again after a failure), checks
its hash and only then moves it into place. Nothing here imports torch: ``data`` runs without it."""

from __future__ import annotations

import contextlib
import json
import logging
import os
import re
import shutil
import sys
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any
from urllib.parse import quote, urlsplit
from urllib.request import url2pathname

import pooch
import requests

from gvbench_nb import GVBenchError
from gvbench_nb.protocol import registry

MANIFEST_PATH = Path(__file__).resolve().parent / "datasets.json"
APP_NAME = "gvbench-nb"
LIST_LABELS = {"what": "what", "licence": "licence", "citation": "cite", "homepage": "source", "where": "get it"}
LIST_LABELS |= {"layout": "layout", "check": "check"}  # in the order `data list` shows them
ATTEMPTS = 4  # tries of one file (a cut connection, bytes that do not match) before the fetch gives up
pooch.get_logger().setLevel(logging.WARNING)  # the commands say what was done, in one line


class DataError(GVBenchError, RuntimeError):
    """A dataset cannot be fetched or checked; the message says which file, where and what to do."""


def data_dir() -> Path:
    """The data folder: ``$GVBENCH_DATA``, else ``data`` in the per-user cache folder."""
    value = os.environ.get("GVBENCH_DATA")
    return Path(value).expanduser().resolve() if value else pooch.os_cache(APP_NAME) / "data"


def cache_dir() -> Path:
    """The feature cache of a run whose params name none: ``$GVBENCH_CACHE``, else ``cache`` in the
    per-user cache folder. It does not follow ``--output-dir``: every output folder shares it."""
    value = os.environ.get("GVBENCH_CACHE")
    return Path(value).expanduser().resolve() if value else pooch.os_cache(APP_NAME) / "cache"


@dataclass(frozen=True)
class DataFile:
    path: str  # relative to the dataset's folder (and so to a mirror's folder of the same name)
    source: str  # relative to the dataset's base_url
    bytes: int
    sha256: str


@dataclass(frozen=True)
class Dataset:
    name: str
    folder: str  # under the data folder
    base_url: str
    files: tuple[DataFile, ...]
    about: dict[str, str]  # title, what, licence, citation, homepage: what `data list` shows

    @property
    def total_bytes(self) -> int:
        return sum(f.bytes for f in self.files)

    def url(self, item: DataFile) -> str:
        return self.base_url + quote(item.source)


def load_manifest(path: Path = MANIFEST_PATH) -> tuple[dict[str, Dataset], dict[str, dict[str, str]]]:
    """The fetchable datasets, and the external ones (title, what, licence, citation, where, layout, check)."""
    raw = json.loads(path.read_text(encoding="utf-8"))
    datasets = {}
    for name, entry in raw["datasets"].items():
        files = tuple(DataFile(**f) for f in entry.pop("files"))
        datasets[name] = Dataset(name, entry.pop("folder"), entry.pop("base_url"), files, entry)
    return datasets, raw["external"]


def get_dataset(name: str, datasets: dict[str, Dataset] | None = None) -> Dataset:
    manifest, external = load_manifest()
    datasets = manifest if datasets is None else datasets
    if name in datasets:
        return datasets[name]
    if name in external:
        raise DataError(
            f"{name} cannot be fetched (no stable per-file URLs): get it from {external[name]['where']} "
            f"and check it with `{external[name]['check']}`"
        )
    hint = " (python -m gvbench_nb data list describes them)"
    raise DataError(registry.unknown_name_message("dataset", name, datasets) + hint)


def presence(dataset: Dataset, root: Path) -> tuple[int, int]:
    """(files present with the right size, files in the manifest) under ``root``; no hashing."""
    paths = [root / dataset.folder / f.path for f in dataset.files]
    found = sum(p.is_file() and p.stat().st_size == f.bytes for p, f in zip(paths, dataset.files, strict=True))
    return found, len(dataset.files)


# ------------------------------------------------------------------- fetching --
def downloader(url: str, progressbar: bool = False) -> Any:
    """pooch's HTTP downloader, or a plain copy for a ``file://`` URL (a mirror folder)."""
    if urlsplit(url).scheme != "file":
        return pooch.HTTPDownloader(progressbar=progressbar)
    return lambda url, output_file, _pooch: shutil.copyfile(url2pathname(urlsplit(url).path), output_file)


def store(dataset: Dataset, root: Path, mirror: str | None) -> pooch.Pooch:
    """The dataset's pooch: its files and hashes, from the public URLs or a mirror with the data folder's layout."""
    if mirror is None:
        base, urls = dataset.base_url, {f.path: dataset.url(f) for f in dataset.files}
    else:
        is_url = urlsplit(mirror).scheme in {"http", "https", "file"}
        base = (mirror if is_url else Path(mirror).expanduser().resolve().as_uri()).rstrip("/") + f"/{dataset.folder}/"
        urls = {f.path: base + quote(f.path) for f in dataset.files}
    hashes = {f.path: f"sha256:{f.sha256}" for f in dataset.files}
    return pooch.create(root / dataset.folder, base, registry=hashes, urls=urls, retry_if_failed=ATTEMPTS - 1)


def root_cause(error: BaseException) -> str:
    while error.__cause__ or error.__context__:
        error = error.__cause__ or error.__context__  # type: ignore[assignment]
    return getattr(error, "strerror", None) or str(error) or type(error).__name__


def fetch_file(dataset: Dataset, item: DataFile, files: pooch.Pooch) -> bool:
    """Place one verified file; False when it was already there and verified (pooch keeps it)."""
    url, label = files.get_url(item.path), f"{dataset.name}: {item.path}"
    try:
        return files.fetch(item.path, lambda _path, action, _pooch: action != "fetch", downloader(url))
    except FileNotFoundError:  # only a mirror folder's copy raises it
        raise DataError(
            f"{label} is missing in the mirror folder (expected {url2pathname(urlsplit(url).path)}); "
            f"pass --mirror a folder holding {dataset.folder}/ with the files of `data fetch`, "
            "or omit --mirror to download from the public source"
        ) from None
    except ValueError as error:  # pooch: the bytes do not have the manifest's hash
        got = re.search(r"but got (\w+)", str(error))
        raise DataError(
            f"{label} from {url} has SHA-256 {got[1] if got else '?'}, but the manifest says {item.sha256}; "
            f"the copy was removed after {ATTEMPTS} attempts: rerun to download it again, and if it fails again "
            "the source has changed (use --mirror with a copy that matches)"
        ) from None
    except requests.HTTPError as error:
        answer = f"HTTP {error.response.status_code} {error.response.reason}"  # type: ignore[union-attr]
        raise DataError(
            f"{label}: {url} answered {answer}; check the address (or that the source still has the file), "
            "or pass --mirror with a folder or URL holding the same layout"
        ) from None
    except requests.ConnectionError as error:
        raise DataError(
            f"{label}: cannot reach {urlsplit(url).netloc or url} ({root_cause(error)}): the network or the "
            f"source is unreachable and nothing was downloaded; pass --mirror DIR with a local copy of the data "
            f"folder (one holding {dataset.folder}/), or run the same command again once the source is reachable"
        ) from None
    except requests.RequestException as error:
        raise DataError(
            f"{label}: could not download {url} after {ATTEMPTS} attempts ({root_cause(error)}); "
            "rerun the same command, or pass --mirror with a local copy"
        ) from None
    except OSError as error:  # the data folder cannot be made or written (pooch's refusal names no reason)
        raise DataError(
            f"{dataset.name}: cannot write {files.abspath / item.path} ({(error.strerror or 'permission denied').lower()}); "
            "set GVBENCH_DATA or pass --to a writable folder"
        ) from None


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
    placed = dict.fromkeys((d.name for d in chosen), 0)
    for dataset in chosen:
        files = store(dataset, root, mirror)
        bar = {"unit": "B", "unit_scale": True, "unit_divisor": 1024, "file": sys.stderr, "disable": not progress}
        with progress_bar(total=dataset.total_bytes, desc=dataset.name, **bar) as shown:
            try:
                for item in dataset.files:
                    placed[dataset.name] += fetch_file(dataset, item, files)
                    shown.update(item.bytes)
            except BaseException:  # leave no empty folder: those holding files placed now stay
                for path in [*sorted((root / dataset.folder).rglob("*"), reverse=True), root / dataset.folder, root]:
                    if path.is_dir() and (path != root or not root_existed):
                        with contextlib.suppress(OSError):
                            path.rmdir()
                raise
    return placed


# ------------------------------------------------------------------- checking --
def images_of_params(params: dict[str, Any]) -> tuple[list[str], str, list[str]]:
    """The images a sequence names (relative to its image root), where the names came from (a builder's
    folders when it has them: its pair file is made from them; else the pair list) and the missing folders."""
    from gvbench_nb.data.sequences import Sequence, folder_images, read_pairs

    options, root = dict(params["builder_options"]), Path(str(params["image_root"]))
    named = [options.get("query_folder"), options.get("reference_folder"), *(options.get("reference_folders") or [])]
    if params["pairs_builder"] and any(named):
        folders = [f for f in named if f]
        names = [n for f in folders if (root / f).is_dir() for n in folder_images(root, f)]
        origin = f"the folders {', '.join(folders)} (the {params['pairs_builder']} builder makes the pairs from them)"
        return names, origin, [f"{f}/" for f in folders if not (root / f).is_dir()]
    pairs = Path(params["pairs"])
    if pairs.is_file():
        return Sequence(params["sequence"], root, read_pairs(pairs)).images, f"the pair list {pairs}", []
    raise DataError(
        f"{params['params_file']}: its pair list {pairs} does not exist; for an official sequence run "
        "`python -m gvbench_nb data fetch gvbench-lists` (or set GVBENCH_DATA to the folder holding gvbench_gt/)"
    )


def fetch_hint(folder: Path) -> str:
    """`data fetch NAME` when ``folder`` is (inside) a dataset's place in the data folder, else ''."""
    for dataset in load_manifest()[0].values():
        place = data_dir() / dataset.folder
        if folder == place or place in folder.parents:
            return f"; run `python -m gvbench_nb data fetch {dataset.name}`"
    return ""


def check_params(params: dict[str, Any], progress: bool = True) -> tuple[bool, str]:
    """Whether every image a loaded params file's sequence names exists and decodes (OpenCV), and a report."""
    import cv2

    from gvbench_nb.data.sequences import PairFileError
    from gvbench_nb.io_utils import progress_bar

    if params["pairs_builder"] == "sample":
        return True, f"{params['sequence']}: its images are rendered by the run (builder sample); nothing to check"
    if params["image_root"] is None:
        raise DataError(
            f"{params['params_file']}: image_root is not set; pass --image-root DIR, the folder the pair paths are "
            "relative to (for the official sequences the one holding day0/, night0/, season1/, ...; see "
            "`python -m gvbench_nb data list`)"
        )
    root = Path(params["image_root"])
    try:
        names, origin, missing_folders = images_of_params(params)
    except PairFileError as error:
        raise DataError(str(error)) from None
    missing, undecodable = [], []
    for name in progress_bar(names, desc="images", unit="img", disable=not progress, file=sys.stderr):
        if not (root / name).is_file():
            missing.append(name)
        elif cv2.imread(str(root / name), cv2.IMREAD_UNCHANGED) is None:
            undecodable.append(name)
    present = len(names) - len(missing)
    lines = [
        f"{params['sequence']}: {len(names)} images named by {origin}, under {root}",
        f"  present {present}, decode {present - len(undecodable)}, missing {len(missing)}, "
        f"do not decode {len(undecodable)}",
    ]
    if missing_folders:
        lines.append(f"  missing folders: {', '.join(missing_folders)}{fetch_hint(root)}")
    if missing:
        official = Path(params["pairs"]).parent == data_dir() / get_dataset("gvbench-lists").folder
        hint = "; the GV-Bench images are not fetchable: `python -m gvbench_nb data list` says where to get them "
        hint += "(gvbench-images) and how to lay them out"
        lines.append("  first missing: " + ", ".join(missing[:10]) + (hint if official else fetch_hint(root)))
    if undecodable:
        lines.append("  first that do not decode: " + ", ".join(undecodable[:10]))
    if not names and not missing_folders:
        lines.append(f"  no images found: check image_root ({root}){fetch_hint(root)}")
    ok = bool(names) and not missing and not undecodable and not missing_folders
    return ok, "\n".join([*lines, "  ok" if ok else "  NOT ready to run"])


# -------------------------------------------------------------------- listing --
def _size(n: int) -> str:
    power = next((p for p in range(3) if n < 1024 ** (p + 1)), 3)
    return f"{n} B" if power == 0 else f"{n / 1024**power:.1f} {('KiB', 'MiB', 'GiB')[power - 1]}"


def list_text(root: Path | None = None) -> str:
    datasets, external = load_manifest()
    root = root if root is not None else data_dir()
    entries = []
    for d in datasets.values():
        found, total = presence(d, root)
        state = "present" if found == total else ("absent" if found == 0 else f"partial ({found}/{total} files)")
        about = {**d.about, "where": f"python -m gvbench_nb data fetch {d.name}"}
        entries.append((d.name, f"{total} files, {_size(d.total_bytes)}; {state} in {root / d.folder}", about))
    entries += [(name, "not fetchable: no stable per-file URLs", about) for name, about in external.items()]
    lines = [f"data folder: {root}  (GVBENCH_DATA, else the per-user cache)", ""]
    for name, state, about in entries:
        lines.append(f"{name}  ({about['title']}; {state})")
        lines += [f"  {label + ':':10}{about[key]}" for key, label in LIST_LABELS.items() if key in about] + [""]
    return "\n".join(lines).rstrip() + "\n"
