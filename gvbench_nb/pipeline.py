"""The one way through: extract once per unique image -> match each pair -> verify ->
per-pair table (``<output_dir>/<method>/pairs.csv``) -> results (``results.csv``).

Every stage reads and writes crash-safe stores (``store.py``), so a rerun resumes
where an interrupted run stopped and evaluation reads only what runs wrote.
"""

from __future__ import annotations

import datetime as _dt
import hashlib
import json
import os
import platform
import sys
import threading
import time
import zlib
from collections import Counter, OrderedDict
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path
from typing import TYPE_CHECKING, Any, TypeVar, cast

import cv2
import numpy as np
import pandas as pd
from tqdm import tqdm

from gvbench_nb import methods as method_registry
from gvbench_nb.data.sequences import Sequence
from gvbench_nb.io_utils import atomic_write_csv, atomic_write_json
from gvbench_nb.protocol.images import (
    ImageReadError,
    load_for_extraction,
    to_original_pixels,
)
from gvbench_nb.protocol.metrics import evaluate_scores
from gvbench_nb.protocol.ransac import verify_matches
from gvbench_nb.runner import record
from gvbench_nb.store import ShardedStore

if TYPE_CHECKING:
    import torch

    from gvbench_nb.protocol.matching.base import PreparedMatcher

# torch and the model modules (extractors, matchers) are imported by the functions that
# run models: a notebook or command that only reads results never pays for them.
T = TypeVar("T")
R = TypeVar("R")

PAIRS_COLUMNS = [
    "pair_index",
    "query",
    "reference",
    "label",
    "method",
    "profile",
    "num_keypoints_query",
    "num_keypoints_reference",
    "num_matches",
    "num_matches_filtered",
    "num_inliers",
    "score",
    "extract_seconds",
    "match_seconds",
    "verify_seconds",
]


def configure_threads(n_threads: int | None = None) -> int:
    """Set torch's and OpenCV's thread count: ``n_threads``, else $GVBENCH_THREADS, else
    every core. On a machine shared with other work, fewer threads than cores can be
    much faster (small matrix products then wait on busy cores); scores do not change."""
    import torch

    n = n_threads or int(os.environ.get("GVBENCH_THREADS") or 0) or os.cpu_count() or 1
    torch.set_num_threads(n)
    cv2.setNumThreads(n)
    return n


JOBS_ENV = "GVBENCH_JOBS"  # the run's parallelism, as `run --jobs` and `bench --jobs` set it
RENAMED_ENV = {"GVBENCH_WORKERS": JOBS_ENV}  # an old name, no longer read: the CLI names its successor


def worker_count(workers: int | None = None) -> int:
    """How many images are extracted, and pairs matched and verified, at once (the run's
    jobs): ``workers``, else $GVBENCH_JOBS (what ``--jobs`` sets), else 1.

    With 1, one image (decoded ahead) and one pair (verified while the next is matched)
    are in flight, so the per-image and per-pair timers are close to each item's own
    cost, which the runtime analyses report. With 2 on a 2-core CPU, throughput rises
    (measured by ``bench``) but the timers include waiting for the shared cores. Scores
    are the same either way.
    """
    text = os.environ.get(JOBS_ENV) or "1"
    try:
        n = workers if workers is not None else int(text)
    except ValueError:
        n = 0
    if n < 1:
        given = n if workers is not None else repr(text)
        raise ValueError(f"jobs must be a whole number of at least 1, got {given} (--jobs or ${JOBS_ENV})")
    return n


def prefetch(
    items: Iterable[T], load: Callable[[T], R], depth: int = 4, workers: int = 2
) -> Iterator[tuple[T, R | BaseException]]:
    """Yield (item, load(item)) in order while the next ``depth`` loads run in threads.

    Decoding and resizing (OpenCV releases the GIL) then overlap the model's compute.
    A failed load is yielded as its exception, in its place, for the caller to raise
    with context.
    """
    iterator = iter(items)
    pending: list[tuple[T, Future[R]]] = []
    with ThreadPoolExecutor(max_workers=workers) as pool:
        for item in iterator:
            pending.append((item, pool.submit(load, item)))
            if len(pending) >= depth:
                break
        while pending:
            item, future = pending.pop(0)
            try:
                result: R | BaseException = future.result()
            except Exception as error:  # surfaced in order by the caller
                result = error
            next_item = next(iterator, None)
            if next_item is not None:
                pending.append((next_item, pool.submit(load, next_item)))
            yield item, result


# ---------------------------------------------------------------- feature cache --
def feature_store(cache_dir: Path, extractor_conf: dict[str, Any]) -> ShardedStore:
    """The cache folder of one extractor conf: ``<cache_dir>/features/<name>-<hash>``."""
    return ShardedStore(
        Path(cache_dir) / "features" / f"{extractor_conf['name']}-{method_registry.conf_hash(extractor_conf)}"
    )


# (resolved path, size, mtime_ns, inode, device) -> content key: a file is hashed again
# only when one of those changes, so a run hashes each image once.
_content_keys: dict[tuple[str, int, int, int, int], str] = {}
_content_keys_lock = threading.Lock()


def content_key(path: str | os.PathLike[str]) -> str:
    """``blake2b-<hex>`` of a file's bytes: the cache key of what the file holds, not where it is."""
    path = Path(path)
    try:
        stat = path.stat()
    except OSError:
        stat = None
    if stat is None or not path.is_file():
        what = "is a folder, not an image file" if path.is_dir() else "not found"
        raise ImageReadError(f"image {what}: {path}; check image_root and the pair file's paths")
    memo = (str(path.resolve()), stat.st_size, stat.st_mtime_ns, stat.st_ino, stat.st_dev)
    with _content_keys_lock:
        known = _content_keys.get(memo)
    if known is not None:
        return known
    digest = hashlib.blake2b(digest_size=20)
    try:
        with open(path, "rb") as stream:
            for block in iter(lambda: stream.read(1 << 20), b""):
                digest.update(block)
    except OSError as error:
        raise ImageReadError(f"cannot read image {path}: {error.strerror or error}") from error
    key = f"blake2b-{digest.hexdigest()}"
    with _content_keys_lock:
        _content_keys[memo] = key
    return key


def image_key(image_root: Path, name: str) -> str:
    """Feature-cache key of image ``name``: its content, so a replaced image or another
    root is extracted again while identical files (any sequence, any path) share an entry.
    The extractor conf is the store's folder name (``feature_store``)."""
    return content_key(Path(image_root) / name)


def first_pair_using(sequence: Sequence, name: str) -> str:
    """'pair N: query reference' of the first pair that uses image ``name`` (for errors)."""
    index, pair = next((i, p) for i, p in enumerate(sequence.pairs) if name in (p.query, p.reference))
    return f"pair {index}: {pair.query} {pair.reference}"


def stored_features(
    features: dict[str, np.ndarray], image: np.ndarray, scale: np.ndarray, store_float16: bool = False
) -> dict[str, np.ndarray]:
    """What the cache holds for one image: keypoints in original pixels, scores,
    descriptors and the original (width, height).

    ``store_float16`` (the extractor conf's key): float32 arrays are stored as float16, as
    hloc's ``extract_features.main(as_half=True)`` stores them, so matching reads the
    rounded values; integer arrays (binary descriptors, the size) stay as they are.
    """
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
    workers: int | None = None,
) -> dict[str, int]:
    """Extract every unique image of ``sequence`` (or only ``images``, a shard of them)
    not yet in the cache, ``workers`` images at a time (default ``worker_count()``).
    Returns counts."""
    store = feature_store(cache_dir, extractor_conf)
    store.refresh()
    wanted: dict[str, str] = {}
    for name in sequence.images if images is None else images:
        try:
            wanted.setdefault(image_key(sequence.image_root, name), name)
        except ImageReadError as error:
            raise ImageReadError(
                f"{error} (image {name!r} of sequence {sequence.name!r}, {first_pair_using(sequence, name)})"
            ) from None
    todo = [key for key in wanted if key not in store]
    counts = {"images": len(wanted), "cached": len(wanted) - len(todo), "extracted": 0}
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

    workers = worker_count(workers)
    # One worker: decoding runs ahead in threads while this thread extracts. Several:
    # each worker decodes and extracts its own image (OpenCV and torch release the GIL).
    # Either way results come back in order and only this thread writes the store.
    if workers == 1:
        results: Iterable[tuple[str, Any]] = (
            (key, loaded if isinstance(loaded, BaseException) else extract(loaded))
            for key, loaded in prefetch(todo, load)
        )
    else:
        results = prefetch(todo, lambda key: extract(load(key)), depth=2 * workers, workers=workers)
    bar = tqdm(total=len(todo), desc=f"extract {extractor_conf['name']}", disable=not progress, unit="img")
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
            counts["extracted"] += 1
            bar.update()
    bar.close()
    return counts


# ---------------------------------------------------------- matching + verifying --
class PreparedCache:
    """Per-image matcher states by image name, least recently used first out once they
    hold more than ``max_bytes`` (the newest state always stays). Thread-safe: a thread
    that asks for an image another thread is preparing waits for that state."""

    def __init__(self, prepare: Callable[[dict[str, np.ndarray]], Any], max_bytes: int = 1 << 30):
        self.prepare, self.max_bytes = prepare, max_bytes
        self._states: OrderedDict[str, tuple[Any, int]] = OrderedDict()
        self._pending: dict[str, Future] = {}
        self._bytes = 0
        self._lock = threading.Lock()

    def get(self, name: str, features: dict[str, np.ndarray]) -> Any:
        with self._lock:
            if name in self._states:
                self._states.move_to_end(name)
                return self._states[name][0]
            pending = self._pending.get(name)
            if pending is None:
                mine = self._pending[name] = Future()
        if pending is not None:
            return pending.result()  # re-raises the preparing thread's error
        try:
            state = self.prepare(features)
        except BaseException as error:
            with self._lock:
                del self._pending[name]
            mine.set_exception(error)
            raise
        size = state.nbytes() if state is not None else 0
        with self._lock:
            del self._pending[name]
            self._states[name] = (state, size)
            self._bytes += size
            while self._bytes > self.max_bytes and len(self._states) > 1:
                _, (_, dropped) = self._states.popitem(last=False)
                self._bytes -= dropped
        mine.set_result(state)
        return state

    def __len__(self) -> int:
        return len(self._states)


class FeatureCache:
    """Feature dicts by image name, read on first use; least recently used first out once
    they hold more than ``max_bytes`` (the newest always stays). Not thread-safe: callers lock."""

    def __init__(self, read: Callable[[str], dict[str, np.ndarray]], max_bytes: int = 256 << 20):
        self.read, self.max_bytes = read, max_bytes
        self._entries: OrderedDict[str, tuple[dict[str, np.ndarray], int]] = OrderedDict()
        self.nbytes = 0

    def get(self, name: str) -> dict[str, np.ndarray]:
        if name in self._entries:
            self._entries.move_to_end(name)
            return self._entries[name][0]
        entry = self.read(name)
        size = sum(value.nbytes for value in entry.values() if isinstance(value, np.ndarray))
        self._entries[name] = (entry, size)
        self.nbytes += size
        while self.nbytes > self.max_bytes and len(self._entries) > 1:
            self.nbytes -= self._entries.popitem(last=False)[1][1]
        return entry

    def __len__(self) -> int:
        return len(self._entries)


def pair_key(image_root: Path, query: str, reference: str, seed: int) -> str:
    """Match-store key of a pair: both images' content keys (a changed image or root
    matches again), their names and the seed (which seed its RANSAC: ``pair_seed``).
    The extractor, matcher and verifier confs are the store's folder name (``match_store``);
    dense matchers have no feature entry, and the content keys serve them the same way."""
    return "\t".join([query, reference, image_key(image_root, query), image_key(image_root, reference), f"seed={seed}"])


def pair_keys(sequence: Sequence, seed: int) -> dict[Any, str]:
    """``pair_key`` of every pair; a missing or unreadable image is named with its pair."""
    keys = {}
    for index, pair in enumerate(sequence.pairs):
        try:
            keys[pair] = pair_key(sequence.image_root, pair.query, pair.reference, seed)
        except ImageReadError as error:
            raise ImageReadError(
                f"{error} (pair {index}: {pair.query} {pair.reference} of sequence {sequence.name!r})"
            ) from None
    return keys


def pair_seed(seed: int, query: str, reference: str) -> int:
    """RANSAC seed of one pair: the same whatever order or shard the pair runs in."""
    return zlib.crc32(f"{seed}\t{query}\t{reference}".encode()) & 0x7FFFFFFF


def method_dir(output_dir: Path, method: str) -> Path:
    return Path(output_dir) / method


UNFINISHED_MARKER = ".unfinished.json"  # in a method folder while a run is making its outputs
FINISHED_OUTPUTS = ("pairs.csv", "run.json")


class ResultsError(FileNotFoundError):
    """An output folder holds no results, or a method's results are unfinished or partial."""


def replaced_profiles(output_dir: Path, methods: Iterable[str], profile: str) -> dict[str, str]:
    """Methods whose finished results in ``output_dir`` are of another profile than ``profile``
    (method -> that profile): a run of theirs there replaces those results."""
    replaced = {}
    for method in methods:
        try:
            run = json.loads((method_dir(output_dir, method) / "run.json").read_text(encoding="utf-8"))
            previous = run["conf"]["profile"]
        except (OSError, ValueError, KeyError, TypeError):
            continue
        if previous != profile:
            replaced[method] = previous
    return replaced


def claim_method_outputs(output_dir: Path, methods: Iterable[str], params_file: str | None = None) -> None:
    """Before any work of a run: remove each method's previous ``pairs.csv`` and
    ``run.json`` (and the folder's ``results.csv``) and mark its folder unfinished, so a
    run that fails at any point leaves nothing that looks like its result."""
    output_dir = Path(output_dir)
    (output_dir / "results.csv").unlink(missing_ok=True)
    for method in methods:
        folder = method_dir(output_dir, method)
        atomic_write_json(
            folder / UNFINISHED_MARKER,
            {
                "started_at": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
                "pid": os.getpid(),
                "host": platform.node(),
                "params_file": params_file,
            },
        )
        for stale in FINISHED_OUTPUTS:
            (folder / stale).unlink(missing_ok=True)


def unfinished_methods(output_dir: Path) -> dict[str, str]:
    """Method folders under ``output_dir`` whose results are not those of one finished
    run: method -> why (a run started and did not finish, or a file of the pair is missing)."""
    problems = {}
    for folder in sorted(p for p in Path(output_dir).iterdir() if p.is_dir()) if Path(output_dir).is_dir() else []:
        marker = folder / UNFINISHED_MARKER
        present = [name for name in FINISHED_OUTPUTS if (folder / name).is_file()]
        if marker.is_file():
            try:
                started = json.loads(marker.read_text(encoding="utf-8")).get("started_at", "?")
            except (OSError, ValueError):
                started = "?"
            problems[folder.name] = f"a run started at {started} has not finished (still running, failed or killed)"
        elif len(present) == 1:
            missing = next(name for name in FINISHED_OUTPUTS if name not in present)
            problems[folder.name] = f"{folder / missing} is missing beside {present[0]}"
    return problems


def check_results_finished(output_dir: Path) -> None:
    """Raise ``ResultsError`` naming each unfinished or partial method folder and what to do."""
    problems = unfinished_methods(output_dir)
    if problems:
        lines = "; ".join(f"{method}: {why}" for method, why in problems.items())
        raise ResultsError(
            f"{output_dir} holds unfinished results ({lines}); run those methods again "
            f"(python -m gvbench_nb run PARAMS --methods {','.join(problems)}) or delete their folders"
        )


def stores_folder(output_dir: Path) -> Path:
    """Where a run's match stores live: its output folder, also while the run's results are
    staged (``record.open_stage``): stores are caches every run of the folder shares, keyed by
    content; only results wait in the stage to be published whole."""
    output_dir = Path(output_dir)
    if record.is_stage(output_dir):
        return output_dir.parent
    return output_dir


def match_store(output_dir: Path, conf: dict[str, Any]) -> ShardedStore:
    """Per-pair matches and inlier masks of one method conf (a changed conf starts afresh)."""
    matching_conf = {k: conf[k] for k in ("extractor", "matcher", "verifier")}
    return ShardedStore(
        method_dir(stores_folder(output_dir), conf["method"]) / f"matches-{method_registry.conf_hash(matching_conf)}"
    )


def match_and_verify(
    sequence: Sequence,
    conf: dict[str, Any],
    cache_dir: Path,
    output_dir: Path,
    device: torch.device | str = "auto",
    seed: int = 0,
    progress: bool = True,
    flush_every: int = 64,
    workers: int | None = None,
) -> dict[str, int]:
    """Match and verify every pair not yet in the method's match store, ``workers``
    pairs at a time (default: ``worker_count()``; dense matchers run one pair at a time)."""
    matches = match_store(output_dir, conf)
    matches.refresh()
    keys = pair_keys(sequence, seed)
    todo = [p for p in sequence.pairs if keys[p] not in matches]
    counts = {"pairs": len(sequence.pairs), "cached": len(sequence.pairs) - len(todo), "matched": 0}
    if not todo:
        return counts
    from gvbench_nb.protocol.features.base import resolve_device
    from gvbench_nb.protocol.matching import build_matcher

    matcher = build_matcher(conf["matcher"], resolve_device(device))
    if method_registry.is_dense(conf):
        _match_dense_pairs(sequence, todo, keys, conf, matcher, matches, seed, progress, flush_every, output_dir)
        counts["matched"] = len(todo)
        return counts
    features = feature_store(cache_dir, conf["extractor"])
    reading = (
        threading.Lock()
    )  # one HDF5 reader at a time (h5py serialises anyway; the handle cache is not thread-safe)

    def read(name: str) -> dict[str, np.ndarray]:
        key = image_key(sequence.image_root, name)
        if key not in features:
            raise KeyError(f"features of {name!r} are not in the cache {features.folder}; run extraction first")
        return features.read(key)

    # A query's candidates are consecutive and references recur: recently read features are
    # kept, up to a memory bound that does not grow with the sequence.
    recent = FeatureCache(read)

    def load(name: str) -> dict[str, np.ndarray]:
        with reading:
            return recent.get(name)

    # A matcher whose per-image work can be done once per image (LightGlue on a CPU:
    # matching/lightglue_prepared.py) gets each image's state from a memory-bounded cache;
    # the first pair using an image is charged for preparing it.
    prepared = (
        PreparedCache(cast("PreparedMatcher", matcher).prepare) if getattr(matcher, "can_prepare", False) else None
    )

    def match_pair(pair: Any) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray], np.ndarray, np.ndarray, float]:
        features0, features1 = load(pair.query), load(pair.reference)
        start = time.perf_counter()
        if prepared is not None:
            pair_matches, match_scores = cast("PreparedMatcher", matcher).match_prepared(
                prepared.get(pair.query, features0), prepared.get(pair.reference, features1)
            )
        else:
            pair_matches, match_scores = matcher(features0, features1)
        return features0, features1, pair_matches, match_scores, time.perf_counter() - start

    def match_and_verify_pair(pair: Any) -> tuple[np.ndarray, np.ndarray, dict[str, Any], float, float]:
        features0, features1, pair_matches, match_scores, match_seconds = match_pair(pair)
        verified, verify_seconds = _verify_pair(
            pair,
            conf,
            seed,
            features0["keypoints"],
            features1["keypoints"],
            pair_matches,
            match_scores,
            image_sizes(features0, features1),
        )
        return pair_matches, match_scores, verified, match_seconds, verify_seconds

    workers = worker_count(workers)
    bar = tqdm(total=len(todo), desc=f"match {conf['method']}", disable=not progress, unit="pair")
    with matches.writer(flush_every) as writer:
        if workers == 1:
            # Matching runs one pair ahead in a worker thread while this thread verifies
            # and writes the previous one: torch and OpenCV release the GIL, so
            # verification overlaps matching. The store is written from this thread only.
            for pair, matched in prefetch(todo, match_pair, depth=2, workers=1):
                if isinstance(matched, BaseException):
                    raise matched
                features0, features1, pair_matches, match_scores, match_seconds = matched
                _verify_and_store(
                    writer,
                    pair,
                    keys[pair],
                    conf,
                    seed,
                    features0["keypoints"],
                    features1["keypoints"],
                    pair_matches,
                    match_scores,
                    {"matches": pair_matches.astype(np.int32)},
                    match_seconds,
                    image_sizes(features0, features1),
                )
                counts["matched"] += 1
                bar.update()
        else:
            # Several pairs at once, each matched then verified in its own thread; results
            # come back in order and are written from this thread only.
            for pair, done in prefetch(todo, match_and_verify_pair, depth=2 * workers, workers=workers):
                if isinstance(done, BaseException):
                    raise done
                pair_matches, match_scores, verified, match_seconds, verify_seconds = done
                _store_verified(
                    writer,
                    keys[pair],
                    pair_matches,
                    match_scores,
                    verified,
                    {"matches": pair_matches.astype(np.int32)},
                    match_seconds,
                    verify_seconds,
                )
                counts["matched"] += 1
                bar.update()
    bar.close()
    return counts


def image_sizes(features0: dict[str, np.ndarray], features1: dict[str, np.ndarray]) -> tuple[Any, Any]:
    """Original (width, height) of both images of a pair, from their cached features."""
    return features0.get("image_size"), features1.get("image_size")


def _verify_and_store(
    writer: Any,
    pair: Any,
    key: str,
    conf: dict[str, Any],
    seed: int,
    keypoints0: np.ndarray,
    keypoints1: np.ndarray,
    pair_matches: np.ndarray,
    match_scores: np.ndarray,
    arrays: dict[str, np.ndarray],
    match_seconds: float,
    sizes: tuple[Any, Any] = (None, None),
) -> None:
    """Verify one matched pair and commit its matches, inlier mask, counts and timings."""
    verified, verify_seconds = _verify_pair(pair, conf, seed, keypoints0, keypoints1, pair_matches, match_scores, sizes)
    _store_verified(writer, key, pair_matches, match_scores, verified, arrays, match_seconds, verify_seconds)


def _verify_pair(
    pair: Any,
    conf: dict[str, Any],
    seed: int,
    keypoints0: np.ndarray,
    keypoints1: np.ndarray,
    pair_matches: np.ndarray,
    match_scores: np.ndarray,
    sizes: tuple[Any, Any] = (None, None),
) -> tuple[dict[str, Any], float]:
    """RANSAC on one pair's matches, seeded by the pair: the verdict and its seconds."""
    start = time.perf_counter()
    verified = verify_matches(
        keypoints0,
        keypoints1,
        pair_matches,
        match_scores,
        conf["verifier"],
        seed=pair_seed(seed, pair.query, pair.reference),
        image_sizes=sizes,
    )
    return verified, time.perf_counter() - start


def _store_verified(
    writer: Any,
    key: str,
    pair_matches: np.ndarray,
    match_scores: np.ndarray,
    verified: dict[str, Any],
    arrays: dict[str, np.ndarray],
    match_seconds: float,
    verify_seconds: float,
    extra_attrs: dict[str, Any] | None = None,
) -> None:
    """Commit one verified pair: its matches, inlier mask, counts and timings."""
    writer.put(
        key,
        {**arrays, "match_scores": match_scores.astype(np.float32), "inlier_mask": verified["inlier_mask"]},
        {
            "num_matches": verified["num_matches"],
            "num_matches_filtered": verified["num_matches_filtered"],
            "num_inliers": verified["num_inliers"],
            "match_seconds": match_seconds,
            "verify_seconds": verify_seconds,
            **(extra_attrs or {}),
        },
    )


def dense_merge_options(matcher_conf: dict[str, Any]) -> dict[str, Any] | None:
    """The keypoint-merging options of a dense matcher conf (``merge_dense_matches``), or
    None when its raw matches are verified pair by pair."""
    if matcher_conf.get("merge_max_keypoints") is None:
        return None
    return {
        "max_keypoints": matcher_conf["merge_max_keypoints"],
        "cell_size": matcher_conf["merge_cell_size"],
        "max_error": matcher_conf["merge_max_error"],
    }


def pair_list_hash(keys: dict[Any, str]) -> str:
    """Identity of a sequence's pair list (its pairs' keys in order): merged dense keypoints
    depend on every pair."""
    return hashlib.sha1("\n".join(keys.values()).encode()).hexdigest()[:10]


def raw_dense_store(output_dir: Path, conf: dict[str, Any]) -> ShardedStore:
    """A dense matcher's raw matches a pair (original pixels), before merging."""
    folder = method_dir(stores_folder(output_dir), conf["method"])
    return ShardedStore(folder / f"raw-{method_registry.conf_hash(conf['matcher'])}")


def check_merged_over(entry: dict[str, Any], sequence: Sequence, keys: dict[Any, str], where: Path) -> None:
    """Merged dense results hold for the pair list they were merged over only."""
    merged_over = entry.get("attr:merged_over")
    if merged_over is not None and str(merged_over) != pair_list_hash(keys):
        raise ValueError(
            f"the dense matches in {where} were merged over another pair list than sequence "
            f"{sequence.name!r} has now ({len(sequence.pairs)} pairs); delete that folder or use another output_dir"
        )


def _match_dense_pairs(
    sequence: Sequence,
    todo: list,
    keys: dict[Any, str],
    conf: dict[str, Any],
    matcher: Callable,
    matches: ShardedStore,
    seed: int,
    progress: bool,
    flush_every: int,
    output_dir: Path | None = None,
) -> None:
    """Dense matchers (LoFTR, ``imm:`` methods) see both images of every pair: no per-image cache.
    Decoding overlaps compute through the same prefetching loader.

    With merging options (``dense_merge_options``), as hloc's ``match_dense``: every pair of
    the sequence is matched first (its raw points kept in ``raw_dense_store``, so a rerun
    resumes), then the keypoints of each image are merged across all pairs
    (``matchers.merge_dense_matches``) and each pair is verified on its merged matches."""

    def load_pair(pair: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        image0, scale0 = load_for_extraction(sequence.image_root / pair.query, conf["matcher"])
        image1, scale1 = load_for_extraction(sequence.image_root / pair.reference, conf["matcher"])
        return image0, scale0, image1, scale1

    def raw_matches(pairs: list) -> Iterator[tuple[Any, np.ndarray, np.ndarray, tuple[Any, Any], np.ndarray, float]]:
        """Each pair's points in original pixels, both images' original sizes, scores, seconds."""
        bar = tqdm(total=len(pairs), desc=f"match {conf['method']}", disable=not progress, unit="pair")
        for pair, loaded in prefetch(pairs, load_pair):
            if isinstance(loaded, BaseException):
                raise ImageReadError(f"{loaded} (pair {pair.query} {pair.reference} of {sequence.name!r})") from loaded
            image0, scale0, image1, scale1 = loaded
            start = time.perf_counter()
            points0, points1, match_scores = matcher(image0, image1)
            points0, points1 = to_original_pixels(points0, scale0), to_original_pixels(points1, scale1)
            seconds = time.perf_counter() - start
            sizes = (np.round(np.array(image0.shape[1::-1]) * scale0), np.round(np.array(image1.shape[1::-1]) * scale1))
            yield pair, points0, points1, sizes, match_scores, seconds
            bar.update()
        bar.close()

    from gvbench_nb.protocol.matching.loftr import merge_dense_matches

    merge = dense_merge_options(conf["matcher"])
    if merge is None:
        with matches.writer(flush_every) as writer:
            for pair, points0, points1, sizes, match_scores, match_seconds in raw_matches(todo):
                identity = np.repeat(np.arange(len(points0))[:, None], 2, axis=1)
                _verify_and_store(
                    writer,
                    pair,
                    keys[pair],
                    conf,
                    seed,
                    points0,
                    points1,
                    identity,
                    match_scores,
                    {"points0": points0, "points1": points1},
                    match_seconds,
                    sizes,
                )
        return

    if output_dir is None:
        raise ValueError("merging dense matches needs the output_dir holding the raw matches")
    for key in matches.keys():
        check_merged_over(matches.read(key, fields=()), sequence, keys, matches.folder)
    raw = raw_dense_store(output_dir, conf)
    raw.refresh()
    with raw.writer(flush_every) as writer:
        for pair, points0, points1, sizes, match_scores, match_seconds in raw_matches(
            [p for p in sequence.pairs if keys[p] not in raw]
        ):
            writer.put(
                keys[pair],
                {
                    "points0": points0,
                    "points1": points1,
                    "scores": match_scores.astype(np.float32),
                    "image_size0": np.asarray(sizes[0]),
                    "image_size1": np.asarray(sizes[1]),
                },
                {"match_seconds": match_seconds},
            )
    raw.refresh()
    entries = [raw.read(keys[p]) for p in sequence.pairs]
    raw.close()
    start = time.perf_counter()
    keypoints, merged = merge_dense_matches(
        [(p.query, p.reference) for p in sequence.pairs],
        [(e["points0"], e["points1"], e["scores"]) for e in entries],
        **merge,
    )
    merge_seconds = (time.perf_counter() - start) / max(len(sequence.pairs), 1)  # shared by every pair
    merged_over = pair_list_hash(keys)
    wanted = {keys[p] for p in todo}
    with matches.writer(flush_every) as writer:
        for pair, entry, (pair_matches, match_scores) in zip(sequence.pairs, entries, merged):
            if keys[pair] not in wanted:
                continue
            points0 = keypoints[pair.query][pair_matches[:, 0]]
            points1 = keypoints[pair.reference][pair_matches[:, 1]]
            verified, verify_seconds = _verify_pair(
                pair,
                conf,
                seed,
                points0,
                points1,
                np.repeat(np.arange(len(points0))[:, None], 2, axis=1),
                match_scores,
                (entry["image_size0"], entry["image_size1"]),
            )
            _store_verified(
                writer,
                keys[pair],
                pair_matches,
                match_scores,
                verified,
                {"points0": points0, "points1": points1},
                float(entry["attr:match_seconds"]) + merge_seconds,
                verify_seconds,
                {"merged_over": merged_over},
            )


def pairs_table(sequence: Sequence, conf: dict[str, Any], cache_dir: Path, output_dir: Path, seed: int) -> pd.DataFrame:
    """The per-pair table of a finished run, built only from the stores."""
    matches = match_store(output_dir, conf)
    matches.refresh()
    dense = method_registry.is_dense(conf)
    uses = Counter(name for pair in sequence.pairs for name in (pair.query, pair.reference))
    image_info: dict[str, tuple[int, float]] = {}
    if not dense:
        features = feature_store(cache_dir, conf["extractor"])
        features.refresh()
        for name in uses:
            entry = features.read(image_key(sequence.image_root, name), fields=("keypoints",))  # not descriptors
            image_info[name] = (len(entry["keypoints"]), float(entry["attr:seconds"]))
        features.close()
    keys = pair_keys(sequence, seed)
    rows = []
    for index, pair in enumerate(sequence.pairs):
        entry = matches.read(keys[pair], fields=())  # the counts and timers only
        if dense:
            check_merged_over(entry, sequence, keys, matches.folder)
        if dense:  # a dense matcher's keypoints are its matches; its whole cost is matching
            keypoints_query = keypoints_reference = int(entry["attr:num_matches"])
            extract_seconds = 0.0
        else:
            keypoints_query, keypoints_reference = image_info[pair.query][0], image_info[pair.reference][0]
            # Extraction is amortised: each image's time is shared among the pairs that use it.
            extract_seconds = sum(image_info[n][1] / uses[n] for n in (pair.query, pair.reference))
        rows.append(
            {
                "pair_index": index,
                "query": pair.query,
                "reference": pair.reference,
                "label": pair.label,
                "method": conf["method"],
                "profile": conf["profile"],
                "num_keypoints_query": keypoints_query,
                "num_keypoints_reference": keypoints_reference,
                "num_matches": int(entry["attr:num_matches"]),
                "num_matches_filtered": int(entry["attr:num_matches_filtered"]),
                "num_inliers": int(entry["attr:num_inliers"]),
                "score": int(entry["attr:num_inliers"]),
                "extract_seconds": extract_seconds,
                "match_seconds": float(entry["attr:match_seconds"]),
                "verify_seconds": float(entry["attr:verify_seconds"]),
            }
        )
    matches.close()
    return pd.DataFrame(rows, columns=PAIRS_COLUMNS)


def cpu_name() -> str:
    """The CPU model (for timings to say what they were measured on)."""
    try:
        with open("/proc/cpuinfo", encoding="utf-8") as handle:
            for line in handle:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def _version(module: str) -> str:
    """A module's ``__version__``, without importing it when it is not loaded yet (importing
    kornia only to read its version takes longer than a small run's work)."""
    if module in sys.modules:
        return sys.modules[module].__version__
    from importlib.metadata import version

    return version(module)


def environment_info(device: torch.device) -> dict[str, Any]:
    import torch

    info = {
        "device": str(device),
        "device_name": torch.cuda.get_device_name(device) if device.type == "cuda" else cpu_name(),
        "cpu_count": os.cpu_count(),
        "torch": torch.__version__,
        "kornia": _version("kornia"),
        "opencv": cv2.__version__,
        "numpy": np.__version__,
        "python": platform.python_version(),
        "platform": platform.platform(),
    }
    return info


def has_pending_work(sequence: Sequence, conf: dict[str, Any], cache_dir: Path, output_dir: Path, seed: int) -> bool:
    """Whether some image of ``sequence`` lacks its features or some pair its verified
    matches, for the method ``conf`` (without building any model)."""
    try:
        if not method_registry.is_dense(conf):
            features = feature_store(cache_dir, conf["extractor"])
            features.refresh()
            if any(image_key(sequence.image_root, name) not in features for name in sequence.images):
                return True
        matches = match_store(output_dir, conf)
        matches.refresh()
        keys = pair_keys(sequence, seed)
        return any(keys[pair] not in matches for pair in sequence.pairs)
    except ImageReadError:  # the computing stages name the image and its pair
        return True


WORK_RECORD = ".computed.json"  # in a method folder: what ``compute_method`` did, until ``run_method`` records it


def _work_identity(sequence: Sequence, conf: dict[str, Any], seed: int, device: str) -> dict[str, Any]:
    """What a work record must match to stand for a run: the same sequence, pairs, conf, seed and device request."""
    identity = {
        "sequence": sequence.name,
        "image_root": str(sequence.image_root),
        "n_pairs": len(sequence.pairs),
        "pairs": sequence.origin,
        "conf": conf,
        "seed": seed,
        "device": str(device),
    }
    return json.loads(json.dumps(identity, sort_keys=True, default=str))  # as it reads back from JSON


def compute_method(
    sequence: Sequence,
    method: str,
    profile: str,
    output_dir: Path,
    cache_dir: Path,
    device: str = "auto",
    seed: int = 0,
    progress: bool = True,
    threads: int | None = None,
    workers: int | None = None,
    verifier: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """Extract and match what the caches lack for one method on a sequence (``run_method``'s
    work, without writing ``pairs.csv`` or ``run.json``). Returns the run record's
    ``environment`` and ``this_run`` and keeps them in the method folder (``WORK_RECORD``),
    so the ``run_method`` that follows (the 02_verify notebook of a ``run``) records this
    work and needs neither torch nor any model."""
    conf = method_registry.resolve_method(method, profile, verifier)
    method_registry.require(method, profile)
    record.claim(output_dir)  # its stores and work record go into the folder: only into one that is the package's
    from gvbench_nb.protocol.features.base import resolve_device

    resolved_device = resolve_device(device)
    configure_threads(threads)
    started = time.perf_counter()
    workers = worker_count(workers)
    extraction = (
        extract_features(sequence, conf["extractor"], cache_dir, resolved_device, progress, workers=workers)
        if conf["extractor"]
        else {"images": 0, "cached": 0, "extracted": 0}
    )
    extracted = time.perf_counter()
    matching = match_and_verify(sequence, conf, cache_dir, output_dir, resolved_device, seed, progress, workers=workers)
    finished = time.perf_counter()
    work = {
        "identity": _work_identity(sequence, conf, seed, device),
        "pid": os.getpid(),
        "environment": environment_info(resolved_device),
        "this_run": {
            "extraction": extraction,
            "matching": matching,
            "workers": workers,
            "extract_wall_seconds": extracted - started,
            "match_verify_wall_seconds": finished - extracted,
        },
    }
    atomic_write_json(method_dir(output_dir, method) / WORK_RECORD, work)
    return work


def _read_work_record(folder: Path, identity: dict[str, Any]) -> dict[str, Any] | None:
    """The work record of this sequence, conf, seed and device request, written by this
    process or its parent (the ``run`` whose notebook this is); a record left by a run that
    stopped before its notebook is not this run's work."""
    try:
        work = json.loads((folder / WORK_RECORD).read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    if work.get("identity") != identity or work.get("pid") not in (os.getpid(), os.getppid()):
        return None
    return work


def run_method(
    sequence: Sequence,
    method: str,
    profile: str,
    output_dir: Path,
    cache_dir: Path,
    device: str = "auto",
    seed: int = 0,
    progress: bool = True,
    threads: int | None = None,
    workers: int | None = None,
    verifier: dict[str, Any] | None = None,
) -> pd.DataFrame:
    """Run one method on a sequence end to end; writes ``pairs.csv`` and ``run.json``.
    ``verifier``: overrides of the profile's verifier conf (``methods.resolve_method``).
    ``workers`` images or pairs run at once (``worker_count``: default $GVBENCH_JOBS or 1).

    Missing weights fail here, before any work. Finished work found in the caches is
    reused, so an interrupted run resumes. When every image and pair is cached and
    ``compute_method`` recorded that work for this sequence, conf, seed and device, that
    record is used and neither torch nor a model is loaded.
    """
    conf = method_registry.resolve_method(method, profile, verifier)
    method_registry.require(method, profile)
    folder = method_dir(output_dir, method)
    # Outside a run's stage (a notebook run on its own), the method writes its results into the
    # output folder in place: only into a folder that is the package's, and one writer at a time
    # while the results are written. The stores are filled first, by any number of processes at
    # once (they are safe for that).
    in_place = not record.is_stage(output_dir)
    written = [f"{method}/{name}" for name in FINISHED_OUTPUTS]
    if in_place:
        record.claim(output_dir)
        record.check_no_foreign_files(output_dir, written)  # never replace a file the package did not write
    with record.pending(output_dir if in_place else None, written):
        # A failed or killed run must not leave the previous run's pairs.csv looking like its result.
        claim_method_outputs(output_dir, [method], sequence.origin.get("params_file"))  # type: ignore[arg-type]
        work = _read_work_record(folder, _work_identity(sequence, conf, seed, device))
        if work is None or has_pending_work(sequence, conf, cache_dir, output_dir, seed):
            work = compute_method(
                sequence, method, profile, output_dir, cache_dir, device, seed, progress, threads, workers, verifier
            )
        lock = record.FolderLock(output_dir) if in_place else None
        if lock is not None:
            lock.acquire(wait_seconds=600)
        try:
            table = pairs_table(sequence, conf, cache_dir, output_dir, seed)
            write_method_outputs(folder, sequence, conf, seed, work["environment"], work["this_run"], table)
            # The record is used once: a later run that finds everything cached records that.
            (folder / WORK_RECORD).unlink(missing_ok=True)
            if in_place:
                record_method_in_place(output_dir, method, sequence)
        finally:
            if lock is not None:
                lock.release()
    return table


def record_method_in_place(output_dir: Path, method: str, sequence: Sequence) -> None:
    """Enter a method's finished outputs, written in place, in the folder's record."""
    with record.editing(output_dir) as entry:
        written = [f"{method}/{name}" for name in FINISHED_OUTPUTS]
        entry["files"].update({name: record.file_sha256(Path(output_dir) / name) for name in written})
        entry["methods"][method] = {**sequence_binding(sequence), "files": written}


def pairs_digest(rows: Iterable[tuple[str, str, int]]) -> str:
    """SHA-256 of the (query, reference, label) rows a method scored, in order: two tables with
    the same digest were scored on the same pairs with the same labels."""
    text = "".join(f"{query}\t{reference}\t{int(label)}\n" for query, reference, label in rows)
    return hashlib.sha256(text.encode()).hexdigest()


def table_pairs_digest(table: pd.DataFrame) -> str:
    return pairs_digest(zip(table["query"], table["reference"], table["label"]))


def images_digest(image_root: Path, names: Iterable[str]) -> str:
    """BLAKE2b of the images' names and content keys: changes when any image's bytes change."""
    digest = hashlib.blake2b(digest_size=20)
    for name in sorted(set(names)):
        digest.update(f"{name}\t{image_key(image_root, name)}\n".encode())
    return digest.hexdigest()


def sequence_binding(sequence: Sequence) -> dict[str, Any]:
    """What a method's results are bound to: the pairs and labels scored, the images' contents,
    and the pair file they came from (as it was then)."""
    return {
        "pairs_digest": pairs_digest((p.query, p.reference, p.label) for p in sequence.pairs),
        "images_digest": images_digest(sequence.image_root, sequence.images),
        "n_pairs": len(sequence.pairs),
        "pairs_file": sequence.origin.get("pairs_file"),
        "pairs_sha256": sequence.origin.get("pairs_sha256"),
    }


def write_method_outputs(
    folder: Path,
    sequence: Sequence,
    conf: dict[str, Any],
    seed: int,
    environment: dict[str, Any],
    this_run: dict[str, Any],
    table: pd.DataFrame,
) -> None:
    """A method's finished outputs: ``run.json``, then ``pairs.csv`` (last: its presence marks a
    finished run, ``methods_with_results``), then the unfinished marker removed."""
    from gvbench_nb import __version__

    atomic_write_json(
        folder / "run.json",
        {
            "sequence": sequence.name,
            "image_root": str(sequence.image_root),
            "n_pairs": len(sequence.pairs),
            "pairs": sequence.origin,
            "binding": sequence_binding(sequence),
            "conf": conf,
            "seed": seed,
            "package_version": __version__,
            "run_id": record.stage_run_id(folder.parent),
            "environment": environment,
            "this_run": this_run,
            "finished_at": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
        },
    )
    atomic_write_csv(folder / "pairs.csv", table)
    (folder / UNFINISHED_MARKER).unlink(missing_ok=True)


# ------------------------------------------------------------------- evaluation --
def params_arguments(params: dict[str, Any]) -> dict[str, Any]:
    """What a loaded params file sets for ``run_method`` and ``compute_method``: profile, output and
    cache folders, device, seed and verifier overrides."""
    return {
        "profile": params["profile"],
        "output_dir": Path(params["output_dir"]),
        "cache_dir": Path(params["cache_dir"]),
        "device": params["device"],
        "seed": params["seed"],
        "verifier": params.get("verifier") or None,
    }


def run_method_of_params(params: dict[str, Any], sequence: Sequence, method: str, **options: Any) -> pd.DataFrame:
    """``run_method`` with what a loaded params file sets: profile, output and cache folders,
    device, seed and verifier overrides (how the CLI, the notebooks and the analyses run a method)."""
    return run_method(sequence, method, **params_arguments(params), **options)


def compute_method_of_params(params: dict[str, Any], sequence: Sequence, method: str, **options: Any) -> dict[str, Any]:
    """``compute_method`` with what a loaded params file sets, as ``run_method_of_params`` runs it."""
    return compute_method(sequence, method, **params_arguments(params), **options)


def load_pairs_table(output_dir: Path, method: str) -> pd.DataFrame:
    path = method_dir(output_dir, method) / "pairs.csv"
    if not path.is_file():
        raise ResultsError(f"no results for method {method!r}: {path} is missing; run the method first")
    return pd.read_csv(path, keep_default_na=False)


def methods_with_results(output_dir: Path) -> list[str]:
    """Methods that have a finished ``pairs.csv``, in registry order, then any others."""
    found = {p.parent.name for p in Path(output_dir).glob("*/pairs.csv")}
    ordered = [m for m in method_registry.METHODS if m in found]
    return ordered + sorted(found - set(ordered))


def timers_source(run: dict[str, Any]) -> str:
    """Whose timers a method's seconds are: ``this run`` (it computed every image and pair),
    ``cached`` (every one came from the cache: the seconds are those of the runs that computed
    them) or ``partly cached``."""
    this_run = run.get("this_run", {})
    extraction, matching = this_run.get("extraction", {}), this_run.get("matching", {})
    reused = extraction.get("cached", 0) + matching.get("cached", 0)
    computed = extraction.get("extracted", 0) + matching.get("matched", 0)
    if not reused:
        return "this run"
    return "cached" if not computed else "partly cached"


def evaluate(output_dir: Path, methods: list[str] | None = None, write: bool = True) -> pd.DataFrame:
    """AP, MR and seconds per pair for every method with results; writes ``results.csv``.

    Every method must have scored the same pairs with the same labels (``pairs_digest``, from
    the pairs tables themselves): a table that mixes pair files is refused, naming the rows."""
    output_dir = Path(output_dir)
    methods = methods or methods_with_results(output_dir)
    if not methods:
        what = "does not exist" if not output_dir.exists() else "holds no method results (<method>/pairs.csv)"
        raise ResultsError(
            f"{output_dir} {what}; give the output_dir of a finished run, or run a method first "
            "(python -m gvbench_nb run PARAMS)"
        )
    rows = []
    for method in methods:
        table = load_pairs_table(output_dir, method)
        run = json.loads((method_dir(output_dir, method) / "run.json").read_text())
        metrics = evaluate_scores(
            table["label"].to_numpy(),
            table["score"].to_numpy(),
            where=f"{method_dir(output_dir, method) / 'pairs.csv'}",
        )
        rows.append(
            {
                "sequence": run["sequence"],
                "method": method,
                "paper_name": run["conf"]["paper_name"],
                "profile": run["conf"]["profile"],
                **metrics,
                "extract_seconds_per_pair": table["extract_seconds"].mean(),
                "match_seconds_per_pair": table["match_seconds"].mean(),
                "verify_seconds_per_pair": table["verify_seconds"].mean(),
                "seconds_per_pair": (
                    table["extract_seconds"] + table["match_seconds"] + table["verify_seconds"]
                ).mean(),
                "device": run["environment"]["device"],
                # >1: the seconds above include waiting for cores shared by concurrent images/pairs
                "workers": run.get("this_run", {}).get("workers", 1),  # runs written before workers existed: 1
                "timers": timers_source(run),
                "pairs_digest": table_pairs_digest(table)[:12],
                "finished_at": run.get("finished_at"),
            }
        )
    results = pd.DataFrame(rows)
    check_one_binding(output_dir, results)
    if write:
        if not record.is_stage(output_dir):
            record.claim(output_dir)
        record.save_checked(output_dir / "results.csv", lambda path: atomic_write_csv(path, results))
    return results


def check_one_binding(output_dir: Path, results: pd.DataFrame) -> None:
    """Refuse a results table whose methods scored different pairs or labels, naming the rows."""
    groups = results.groupby("pairs_digest", sort=False)["method"].apply(list)
    if len(groups) > 1:
        described = "; ".join(f"{', '.join(names)}: pairs {digest}" for digest, names in groups.items())
        raise ResultsError(
            f"{output_dir}: its methods were scored on different pairs or labels ({described}), so their AP and MR "
            "do not compare; rerun them on one pair file, or give each pair file its own output_dir"
        )


def changed_inputs(output_dir: Path, methods: Iterable[str]) -> dict[str, str]:
    """Methods whose inputs changed since they ran: method -> what changed (the pair file's
    SHA-256, or the images' contents); inputs no longer there to check are not reported."""
    changed = {}
    for method in methods:
        run = json.loads((method_dir(output_dir, method) / "run.json").read_text(encoding="utf-8"))
        pairs = run.get("pairs") or {}
        pairs_file = pairs.get("pairs_file")
        if pairs_file and Path(pairs_file).is_file() and record.file_sha256(pairs_file) != pairs.get("pairs_sha256"):
            changed[method] = f"the pair file {pairs_file} changed"
            continue
        recorded = (run.get("binding") or {}).get("images_digest")
        root = Path(run.get("image_root", ""))
        if recorded and root.is_dir():
            table = load_pairs_table(output_dir, method)
            try:
                now = images_digest(root, [*table["query"], *table["reference"]])
            except ImageReadError:
                changed[method] = f"an image under {root} is gone"
                continue
            if now != recorded:
                changed[method] = f"images under {root} changed"
    return changed


def check_results_current(output_dir: Path, methods: Iterable[str], tables: Iterable[str] = ()) -> None:
    """Raise unless ``methods``' results in ``output_dir`` are what a finished run published
    (the folder's record), unedited (their files' SHA-256 are the record's; ``tables``: more such
    files, e.g. ``results.csv``), from a pair file and images unchanged since."""
    output_dir = Path(output_dir)
    methods = list(methods)
    record.check_published(output_dir)
    names = [f"{m}/{name}" for m in methods for name in FINISHED_OUTPUTS] + list(tables)
    edited = record.changed_files(output_dir, names)
    if edited:
        raise record.RecordError(
            f"{output_dir}: {', '.join(edited)} changed since gvbench-nb wrote them, so their scores are not a "
            f"run's; run those methods again (python -m gvbench_nb run PARAMS --output-dir {output_dir}) after "
            "moving the edited files away"
        )
    check_inputs_unchanged(output_dir, methods)


def check_inputs_unchanged(output_dir: Path, methods: Iterable[str]) -> None:
    """``ResultsError`` naming the methods whose pair file or images changed since they ran."""
    changed = changed_inputs(output_dir, methods)
    if changed:
        described = "; ".join(f"{method}: {why}" for method, why in changed.items())
        raise ResultsError(
            f"{output_dir}: results computed from inputs that have changed since ({described}); run those methods "
            f"again (python -m gvbench_nb run PARAMS --methods {','.join(changed)} --output-dir {output_dir})"
        )
