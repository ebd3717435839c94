"""Features once per unique image content: the content-keyed feature cache and its extraction loop."""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import stat
import threading
import time
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from gvbench_nb import methods as method_registry
from gvbench_nb.data.sequences import Sequence
from gvbench_nb.io_utils import atomic_write_json, hash_file, progress_bar
from gvbench_nb.protocol import weights
from gvbench_nb.protocol.images import ImageReadError, load_for_extraction, to_original_pixels
from gvbench_nb.runner import concurrency
from gvbench_nb.runner.store import ShardedStore

if TYPE_CHECKING:
    import torch


# ---------------------------------------------------------------- feature cache --
def checkpoints_of(*confs: dict[str, Any] | None) -> list[str]:
    """The checkpoints the stage confs load (an extractor, a matcher), each once."""
    return list(dict.fromkeys(name for conf in confs if conf for name in conf.get("checkpoints", ())))


def weights_conf_hash(conf: dict[str, Any], checkpoints: list[str]) -> str:
    """A stage's cache identity: its conf's hash, with the git blob ids of the weights it loads, so other
    bytes at a checkpoint's path never reuse what these computed (no weights: the conf's own hash)."""
    held = {file: entry["blob"] for file, entry in weights.held_weights(checkpoints).items()}
    return method_registry.conf_hash({**conf, "weights": held} if held else conf)


def feature_store(cache_dir: Path, extractor_conf: dict[str, Any]) -> ShardedStore:
    """The cache folder of one extractor conf and its weights: ``<cache_dir>/features/<name>-<hash>``."""
    identity = weights_conf_hash(extractor_conf, checkpoints_of(extractor_conf))
    return ShardedStore(Path(cache_dir) / "features" / f"{extractor_conf['name']}-{identity}")


# run id -> (store folder, key) of every image that run extracted in this process: a later method
# of the same run that finds them cached is served by this run's own work, timed by this run.
_extracted_by_run: dict[str, set[tuple[str, str]]] = {}


# In the cache folder: absolute path -> [size, mtime_ns, inode, ctime_ns, key].
CONTENT_KEYS_FILE = "content-keys.json"

# This process's content keys by absolute path, each with the size, mtime, inode and ctime it was hashed
# at: a file is hashed again when one of them changes (a rewrite in place that restores size and mtime
# still moves the ctime, which no user can set).
_known_keys: dict[str, tuple[int, int, int, int, str]] = {}

_known_lock = threading.Lock()


def content_key(path: str | os.PathLike[str]) -> str:
    """``blake2b-<hex>`` of a file's bytes: the cache key of what the file holds, not where it is."""
    absolute = os.path.abspath(path)
    try:
        status = os.stat(absolute)
    except OSError:
        status = None
    if status is None or not stat.S_ISREG(status.st_mode):
        what = "is a folder, not an image file" if Path(path).is_dir() else "not found"
        raise ImageReadError(f"image {what}: {path}; check image_root and the pair file's paths")
    seen = (status.st_size, status.st_mtime_ns, status.st_ino, status.st_ctime_ns)
    known = _known_keys.get(absolute)
    if known is not None and known[:4] == seen:
        return known[4]
    try:
        key = f"blake2b-{hash_file(path, hashlib.blake2b(digest_size=20))}"
    except OSError as error:
        raise ImageReadError(f"cannot read image {path}: {error.strerror or error}") from error
    with _known_lock:
        _known_keys[absolute] = (*seen, key)
    return key


def image_key(image_root: Path, name: str) -> str:
    """Feature-cache key of image ``name``: its content, so a replaced image or another
    root is extracted again while identical files (any sequence, any path) share an entry.
    The extractor conf is the store's folder name (``feature_store``)."""
    return content_key(os.path.join(image_root, name))


def _saved_keys(cache_dir: Path) -> dict[str, tuple[int, int, int, int, str]]:
    try:
        saved = json.loads((cache_dir / CONTENT_KEYS_FILE).read_text(encoding="utf-8"))
        return {p: (e[0], e[1], e[2], e[3], e[4]) for p, e in saved.items() if isinstance(e, list) and len(e) == 5}
    except (OSError, ValueError, AttributeError):  # none, damaged, or not a mapping: a memo only
        return {}


def reuse_saved_keys(cache_dir: str | os.PathLike[str]) -> dict[str, tuple[int, int, int, int, str]]:
    """Take the content keys other processes saved in ``cache_dir`` (``CONTENT_KEYS_FILE``), each used
    while its file's size, mtime, inode and ctime are still those it was hashed at; returns what was saved."""
    saved = _saved_keys(Path(cache_dir))
    with _known_lock:
        for path, entry in saved.items():
            _known_keys.setdefault(path, entry)
    return saved


def image_keys(
    sequence: Sequence, cache_dir: str | os.PathLike[str] | None = None, images: Iterable[str] | None = None
) -> dict[str, str]:
    """Image name -> content key of the sequence's images (or ``images``); a missing or unreadable one is
    named with its first pair. With ``cache_dir``, the keys other processes hashed there are reused
    (while their file's size, mtime, inode and ctime hold) and this call's are added (``CONTENT_KEYS_FILE``)."""
    saved = reuse_saved_keys(cache_dir) if cache_dir is not None else {}
    keys = {}
    for name in sequence.images if images is None else images:
        try:
            keys[name] = image_key(sequence.image_root, name)
        except ImageReadError as error:
            raise ImageReadError(
                f"{error} (image {name!r} of sequence {sequence.name!r}, {first_pair_using(sequence, name)})"
            ) from None
    if cache_dir is not None:
        paths = [os.path.abspath(os.path.join(sequence.image_root, name)) for name in keys]
        if any(saved.get(path) != _known_keys[path] for path in paths):
            _save_keys(Path(cache_dir), {path: _known_keys[path] for path in paths})
    return keys


def _save_keys(cache_dir: Path, entries: dict[str, tuple[int, int, int, int, str]]) -> None:
    """Merge ``entries`` into the cache folder's content-keys file: one writer at a time (a file lock),
    the file replaced whole; a folder that is not there or cannot be written keeps none (a memo only)."""
    from filelock import FileLock

    if cache_dir.is_dir():  # the lock's Timeout is an OSError too
        with contextlib.suppress(OSError), FileLock(str(cache_dir / f"{CONTENT_KEYS_FILE}.lock"), timeout=60):
            atomic_write_json(cache_dir / CONTENT_KEYS_FILE, {**_saved_keys(cache_dir), **entries})


def content_keys(sequence: Sequence, cache_dir: str | os.PathLike[str] | None = None) -> set[str]:
    """The different contents of the sequence's images: byte-identical files are one, extracted once."""
    return set(image_keys(sequence, cache_dir).values())


def first_pair_using(sequence: Sequence, name: str) -> str:
    """'pair N: query reference' of the first pair that uses image ``name`` (for errors)."""
    index, pair = next((i, p) for i, p in enumerate(sequence.pairs) if name in (p.query, p.reference))
    return f"pair {index}: {pair.query} {pair.reference}"


def stored_features(
    features: dict[str, np.ndarray], image: np.ndarray, scale: np.ndarray, store_float16: bool = False
) -> dict[str, np.ndarray]:
    """What the cache holds for one image: keypoints in original pixels, scores, descriptors, size;
    ``store_float16``: float32 arrays as float16, as hloc's ``extract_features.main(as_half=True)``."""
    stored = {
        "keypoints": to_original_pixels(features["keypoints"], scale),
        "scores": features["scores"],
        "descriptors": features["descriptors"],
        "image_size": np.round(np.array(image.shape[1::-1]) * scale).astype(np.int64),
    }
    if store_float16:
        stored = {k: v.astype(np.float16) if v.dtype == np.float32 else v for k, v in stored.items()}
    return stored


def extract_features(
    sequence: Sequence,
    extractor_conf: dict[str, Any],
    cache_dir: Path,
    device: torch.device | str = "auto",
    progress: bool = True,
    flush_every: int = 16,
    images: list[str] | None = None,
    jobs: int | None = None,
    run_id: str | None = None,
) -> dict[str, int]:
    """Extract the images of ``sequence`` (or ``images``) not yet cached, ``jobs`` at a time; counts,
    with ``cached_by_this_run``: cached images run ``run_id`` extracted itself, for another method."""
    store = feature_store(cache_dir, extractor_conf)
    store.refresh()
    wanted: dict[str, str] = {}
    for name, key in image_keys(sequence, cache_dir, images).items():
        wanted.setdefault(key, name)
    todo = [key for key in wanted if key not in store]
    ours = _extracted_by_run.setdefault(run_id, set()) if run_id else set()
    earlier = len(ours & {(str(store.folder), key) for key in wanted}) if ours else 0
    counts = {"images": len(wanted), "cached": len(wanted) - len(todo), "extracted": 0}
    if earlier:
        counts["cached_by_this_run"] = earlier
    if not todo:
        return counts
    from gvbench_nb.protocol.features import build_extractor
    from gvbench_nb.protocol.features.base import resolve_device

    extractor = build_extractor(extractor_conf, resolve_device(device))

    def load(key: str) -> tuple[np.ndarray, np.ndarray]:
        try:
            return load_for_extraction(Path(sequence.image_root) / wanted[key], extractor_conf)
        except Exception as error:  # whatever decoding raised, it is this image's fault
            if isinstance(error, ImageReadError):
                raise
            raise ImageReadError(str(error)) from error

    def extract(loaded: tuple[np.ndarray, np.ndarray]) -> tuple[dict[str, np.ndarray], float]:
        image, scale = loaded
        start = time.perf_counter()
        features = extractor(image)
        stored = stored_features(features, image, scale, extractor_conf.get("store_float16", False))
        return stored, time.perf_counter() - start

    results = _extract_in_order(todo, load, extract, concurrency.job_count(jobs))
    bar = progress_bar(total=len(todo), desc=f"extract {extractor_conf['name']}", disable=not progress, unit="img")
    with store.writer(flush_every) as writer:
        for key, extracted in results:
            if isinstance(extracted, ImageReadError):
                raise ImageReadError(
                    f"{extracted} (image {wanted[key]!r} of sequence {sequence.name!r}, "
                    f"{first_pair_using(sequence, wanted[key])})"
                ) from extracted
            if isinstance(extracted, BaseException):
                raise extracted
            features, seconds = extracted
            writer.put(key, features, {"seconds": seconds})
            ours.add((str(store.folder), key))
            counts["extracted"] += 1
            bar.update()
    bar.close()
    return counts


def _extract_in_order(todo: list[str], load: Callable, extract: Callable, jobs: int) -> Iterable[tuple[str, Any]]:
    """(key, features and seconds, or the error) in ``todo``'s order. One job: decoding runs
    ahead in threads while this thread extracts; several: each decodes and extracts its own
    image (OpenCV and torch release the GIL). Only the caller's thread writes the store."""
    if jobs == 1:
        return (
            (key, loaded if isinstance(loaded, BaseException) else extract(loaded))
            for key, loaded in concurrency.prefetch(todo, load)
        )
    return concurrency.prefetch(todo, lambda key: extract(load(key)), depth=2 * jobs, jobs=jobs)
