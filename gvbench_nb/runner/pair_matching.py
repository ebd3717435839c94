"""Match and verify each pair (sparse, or dense with hloc's merging) into a content-keyed match store."""

from __future__ import annotations

import hashlib
import threading
import time
import zlib
from collections.abc import Callable, Iterator
from concurrent.futures import Future
from pathlib import Path
from typing import TYPE_CHECKING, Any, cast

import numpy as np
from cachetools import LRUCache

from gvbench_nb import methods as method_registry
from gvbench_nb.data.sequences import Sequence
from gvbench_nb.io_utils import progress_bar
from gvbench_nb.protocol.images import ImageReadError, load_for_extraction, to_original_pixels
from gvbench_nb.protocol.ransac import verify_matches
from gvbench_nb.runner import concurrency, image_features
from gvbench_nb.runner.store import ShardedStore

if TYPE_CHECKING:
    import torch

    from gvbench_nb.protocol.matching.base import PreparedMatcher

# The match store's counts of distinct keypoints among a pair's inliers (docs/protocol.md, "Collapsed
# inliers"); a per-pair table's columns carry the same names (``method_outputs``, which imports no stage).
INLIER_KEYPOINT_COUNTS = ("num_inlier_keypoints_query", "num_inlier_keypoints_reference")


def _bounded_lru(max_bytes: int, size_of: Callable[[Any], int]) -> LRUCache:
    """An LRU of at most ``max_bytes``; an entry counts 1 to ``max_bytes``, so the newest always stays."""
    return LRUCache(maxsize=max_bytes, getsizeof=lambda value: min(max(size_of(value), 1), max_bytes))


class PreparedCache:
    """Per-image matcher states in a byte-bounded LRU; a thread asking for one being prepared waits."""

    def __init__(self, prepare: Callable[[dict[str, np.ndarray]], Any], max_bytes: int = 1 << 30):
        self.prepare = prepare
        self._states = _bounded_lru(max_bytes, lambda state: state.nbytes() if state is not None else 0)
        self._pending: dict[str, Future] = {}
        self._lock = threading.Lock()

    def get(self, name: str, features: dict[str, np.ndarray]) -> Any:
        with self._lock:
            if name in self._states:
                return self._states[name]
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
        with self._lock:
            del self._pending[name]
            self._states[name] = state
        mine.set_result(state)
        return state

    def __len__(self) -> int:
        return len(self._states)


class FeatureCache:
    """Feature dicts by image name, read on first use, in a byte-bounded LRU; one thread reads at a time
    (h5py serialises reads anyway, and a store's handle cache is not thread-safe)."""

    def __init__(self, read: Callable[[str], dict[str, np.ndarray]], max_bytes: int = 256 << 20):
        self.read = read
        self._entries = _bounded_lru(
            max_bytes, lambda entry: sum(v.nbytes for v in entry.values() if isinstance(v, np.ndarray))
        )
        self._lock = threading.Lock()

    @property
    def nbytes(self) -> int:
        return int(self._entries.currsize)

    def get(self, name: str) -> dict[str, np.ndarray]:
        with self._lock:
            if name not in self._entries:
                self._entries[name] = self.read(name)
            return self._entries[name]

    def __len__(self) -> int:
        return len(self._entries)


def pair_key(image_root: Path, query: str, reference: str, seed: int) -> str:
    """Match-store key of a pair: names, both images' content keys (a changed image matches again), seed."""
    keys = image_features.image_key(image_root, query), image_features.image_key(image_root, reference)
    return _joined_key(query, reference, *keys, seed)


def _joined_key(query: str, reference: str, query_key: str, reference_key: str, seed: int) -> str:
    return "\t".join([query, reference, query_key, reference_key, f"seed={seed}"])


# (image root, pairs, seed) -> the images' content keys and the pairs' keys made of them, for the last few
# pair lists: a run asks for them at each stage, and they are made again only when an image's content changed.
_made_pair_keys: LRUCache = LRUCache(maxsize=4)
_made_pair_keys_lock = threading.Lock()  # Dask's threaded workers share the process


def pair_keys(sequence: Sequence, seed: int) -> dict[Any, str]:
    """``pair_key`` of every pair; a missing or unreadable image is named with its first pair."""
    contents = image_features.image_keys(sequence)
    memo = (str(sequence.image_root), tuple(sequence.pairs), seed)
    with _made_pair_keys_lock:
        made = _made_pair_keys.get(memo)
        if made is None or made[0] != contents:
            keys = {
                pair: _joined_key(pair.query, pair.reference, contents[pair.query], contents[pair.reference], seed)
                for pair in sequence.pairs
            }
            made = _made_pair_keys[memo] = (contents, keys)
    return dict(made[1])


def pair_seed(seed: int, query: str, reference: str) -> int:
    """RANSAC seed of one pair: the same whatever order or shard the pair runs in."""
    return zlib.crc32(f"{seed}\t{query}\t{reference}".encode()) & 0x7FFFFFFF


def match_store(cache_dir: Path, conf: dict[str, Any], keys: dict[Any, str] | None = None) -> ShardedStore:
    """Per-pair matches and inlier masks of one method conf, in the cache folder:
    ``<cache_dir>/matches/<method>-<conf and weights hash>`` (a changed conf or weights start afresh; the pair keys hold the
    images' contents and the seed, so every output folder shares it). A dense conf merging keypoints
    across pairs (``dense_merge_options``) has a store for each pair list (``keys``, ``pair_keys``)."""
    matching_conf = {k: conf[k] for k in ("extractor", "matcher", "verifier")}
    checkpoints = image_features.checkpoints_of(conf["extractor"], conf["matcher"])
    name = f"{conf['method']}-{image_features.weights_conf_hash(matching_conf, checkpoints)}"
    if dense_merge_options(conf["matcher"]) is not None:
        if keys is None:
            raise ValueError(f"the match store of {conf['method']!r} is chosen by its pair list: pass its pair keys")
        name += f"-over-{pair_list_hash(keys)}"
    return ShardedStore(Path(cache_dir) / "matches" / name)


def match_and_verify(
    sequence: Sequence,
    conf: dict[str, Any],
    cache_dir: Path,
    device: torch.device | str = "auto",
    seed: int = 0,
    progress: bool = True,
    flush_every: int = 64,
    jobs: int | None = None,
) -> dict[str, int]:
    """Match and verify every pair not yet in the match store, ``jobs`` at a time (dense: one)."""
    keys = pair_keys(sequence, seed)
    matches = match_store(cache_dir, conf, keys)
    matches.refresh()
    todo = [p for p in sequence.pairs if keys[p] not in matches]
    counts = {"pairs": len(sequence.pairs), "cached": len(sequence.pairs) - len(todo), "matched": 0}
    if not todo:
        return counts
    from gvbench_nb.protocol.features.base import resolve_device
    from gvbench_nb.protocol.matching import build_matcher

    matcher = build_matcher(conf["matcher"], resolve_device(device))
    if method_registry.is_dense(conf):
        _match_dense_pairs(sequence, todo, keys, conf, matcher, matches, seed, progress, flush_every, cache_dir)
        counts["matched"] = len(todo)
        return counts
    features = image_features.feature_store(cache_dir, conf["extractor"])

    def read(name: str) -> dict[str, np.ndarray]:
        key = image_features.image_key(sequence.image_root, name)
        if key not in features:
            raise KeyError(f"features of {name!r} are not in the cache {features.folder}; run extraction first")
        return features.read(key)

    recent = FeatureCache(read)  # a query's candidates are consecutive and references recur
    # Per-image work done once per image (LightGlue on a CPU); the first pair using it pays for it.
    prepared = (
        PreparedCache(cast("PreparedMatcher", matcher).prepare) if getattr(matcher, "can_prepare", False) else None
    )

    def match_and_verify_pair(pair: Any) -> tuple[np.ndarray, np.ndarray, dict[str, Any], float]:
        features0, features1 = recent.get(pair.query), recent.get(pair.reference)
        start = time.perf_counter()
        if prepared is not None:
            pair_matches, match_scores = cast("PreparedMatcher", matcher).match_prepared(
                prepared.get(pair.query, features0), prepared.get(pair.reference, features1)
            )
        else:
            pair_matches, match_scores = matcher(features0, features1)
        match_seconds = time.perf_counter() - start
        keypoints = features0["keypoints"], features1["keypoints"]
        sizes = features0.get("image_size"), features1.get("image_size")  # original (width, height)
        verified = _verify_pair(pair, conf, seed, *keypoints, pair_matches, match_scores, sizes)
        return pair_matches, match_scores, verified, match_seconds

    # Worker threads match and verify ahead (torch and OpenCV release the GIL); this one writes, in order.
    jobs = concurrency.job_count(jobs)
    bar = progress_bar(total=len(todo), desc=f"match {conf['method']}", disable=not progress, unit="pair")
    with matches.writer(flush_every) as writer:
        for pair, done in concurrency.prefetch(todo, match_and_verify_pair, depth=2 * jobs, jobs=jobs):
            if isinstance(done, BaseException):
                raise done
            pair_matches, match_scores, verified, match_seconds = done
            arrays = {"matches": pair_matches.astype(np.int32), "match_scores": match_scores.astype(np.float32)}
            _store_verified(writer, keys[pair], arrays, verified, match_seconds)
            counts["matched"] += 1
            bar.update()
    bar.close()
    return counts


def _verify_pair(
    pair: Any,
    conf: dict[str, Any],
    seed: int,
    keypoints0: np.ndarray,
    keypoints1: np.ndarray,
    pair_matches: np.ndarray,
    match_scores: np.ndarray,
    sizes: tuple[Any, Any] = (None, None),
) -> dict[str, Any]:
    """RANSAC on one pair's matches, seeded by the pair: the verdict, with its ``verify_seconds``."""
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
    return {**verified, "verify_seconds": time.perf_counter() - start}


def inlier_keypoint_counts(arrays: dict[str, np.ndarray], inlier_mask: np.ndarray) -> dict[str, int]:
    """Distinct query and reference keypoints among a pair's inliers: by keypoint index (``matches``), or
    by coordinates (``points0``, ``points1``) for a dense matcher, whose points have no index."""
    mask = np.asarray(inlier_mask, dtype=bool)
    if "matches" in arrays:
        matched = np.asarray(arrays["matches"]).reshape(-1, 2)
        sides = matched[mask, :1], matched[mask, 1:]
    else:
        sides = np.asarray(arrays["points0"])[mask], np.asarray(arrays["points1"])[mask]
    return {name: len(np.unique(side, axis=0)) for name, side in zip(INLIER_KEYPOINT_COUNTS, sides)}


def stored_counts(matches: ShardedStore, key: str) -> dict[str, Any]:
    """One pair's counts and timers as ``attr:NAME``; an entry stored without its inlier keypoint counts
    has them counted from its stored matches and inlier mask."""
    entry: dict[str, Any] = matches.read(key, fields=())
    if any(f"attr:{name}" not in entry for name in INLIER_KEYPOINT_COUNTS):
        stored = matches.read(key, fields=("matches", "points0", "points1", "inlier_mask"))
        counted = inlier_keypoint_counts(stored, stored["inlier_mask"])
        entry.update({f"attr:{name}": count for name, count in counted.items()})
    return entry


def _store_verified(
    writer: Any, key: str, arrays: dict[str, np.ndarray], verified: dict[str, Any], match_seconds: float, **extra: Any
) -> None:
    """Commit one verified pair: its matches (``arrays``) and inlier mask, its counts and timings."""
    counts = {name: verified[name] for name in ("num_matches", "num_matches_filtered", "num_inliers")}
    counts.update(inlier_keypoint_counts(arrays, verified["inlier_mask"]))
    timings = {"match_seconds": match_seconds, "verify_seconds": verified["verify_seconds"]}
    writer.put(key, {**arrays, "inlier_mask": verified["inlier_mask"]}, {**counts, **timings, **extra})


def dense_merge_options(matcher_conf: dict[str, Any]) -> dict[str, Any] | None:
    """A dense matcher conf's keypoint-merging options, or None when pairs are verified one by one."""
    if matcher_conf.get("merge_max_keypoints") is None:
        return None
    return {
        "max_keypoints": matcher_conf["merge_max_keypoints"],
        "cell_size": matcher_conf["merge_cell_size"],
        "max_error": matcher_conf["merge_max_error"],
    }


def pair_list_hash(keys: dict[Any, str]) -> str:
    """Identity of a sequence's pair list: merged dense keypoints depend on every pair."""
    return hashlib.sha1("\n".join(keys.values()).encode()).hexdigest()[:10]


def raw_dense_store(cache_dir: Path, conf: dict[str, Any]) -> ShardedStore:
    """A dense matcher's raw matches a pair (original pixels), before merging, in the cache folder:
    ``<cache_dir>/raw-matches/<method>-<matcher conf hash>``."""
    identity = image_features.weights_conf_hash(conf["matcher"], image_features.checkpoints_of(conf["matcher"]))
    return ShardedStore(Path(cache_dir) / "raw-matches" / f"{conf['method']}-{identity}")


def _dense_raw_matches(
    sequence: Sequence, pairs: list, conf: dict[str, Any], matcher: Callable, progress: bool
) -> Iterator[tuple[Any, np.ndarray, np.ndarray, tuple[Any, Any], np.ndarray, float]]:
    """Each pair's points in original pixels, original sizes, scores, seconds (decoding prefetched)."""
    # A matcher with a loader of its own (vismatch's) sees the images as that loader makes them.
    load = getattr(matcher, "load", None) or (lambda path: load_for_extraction(path, conf["matcher"]))

    def load_pair(pair: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        return (*load(sequence.image_root / pair.query), *load(sequence.image_root / pair.reference))

    bar = progress_bar(total=len(pairs), desc=f"match {conf['method']}", disable=not progress, unit="pair")
    for pair, loaded in concurrency.prefetch(pairs, load_pair):
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


def _identity(count: int) -> np.ndarray:
    return np.repeat(np.arange(count)[:, None], 2, axis=1)


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
    cache_dir: Path,
) -> None:
    """Dense matchers (LoFTR, ``imm:``): merged as hloc's ``match_dense`` when the conf says so, else
    each pair's raw matches are verified as they come."""
    merge = dense_merge_options(conf["matcher"])
    if merge is not None:
        raw = raw_dense_store(cache_dir, conf)
        _merge_and_verify_dense(sequence, todo, keys, conf, matcher, matches, raw, merge, seed, progress, flush_every)
        return
    with matches.writer(flush_every) as writer:
        for pair, points0, points1, sizes, match_scores, match_seconds in _dense_raw_matches(
            sequence, todo, conf, matcher, progress
        ):
            identity = _identity(len(points0))
            verified = _verify_pair(pair, conf, seed, points0, points1, identity, match_scores, sizes)
            arrays = {"points0": points0, "points1": points1, "match_scores": match_scores.astype(np.float32)}
            _store_verified(writer, keys[pair], arrays, verified, match_seconds)


def _merge_and_verify_dense(
    sequence: Sequence,
    todo: list,
    keys: dict[Any, str],
    conf: dict[str, Any],
    matcher: Callable,
    matches: ShardedStore,
    raw: ShardedStore,
    merge: dict[str, Any],
    seed: int,
    progress: bool,
    flush_every: int,
) -> None:
    """Match every pair (raw points kept in ``raw`` so a rerun resumes), merge each image's keypoints
    across all pairs, then verify each pair on its merged matches."""
    from gvbench_nb.protocol.matching.loftr import merge_dense_matches

    raw.refresh()
    with raw.writer(flush_every) as writer:
        missing = [p for p in sequence.pairs if keys[p] not in raw]
        for pair, points0, points1, sizes, match_scores, match_seconds in _dense_raw_matches(
            sequence, missing, conf, matcher, progress
        ):
            arrays = {"points0": points0, "points1": points1, "scores": match_scores.astype(np.float32)}
            sized = {"image_size0": np.asarray(sizes[0]), "image_size1": np.asarray(sizes[1])}
            writer.put(keys[pair], {**arrays, **sized}, {"match_seconds": match_seconds})
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
            sizes = (entry["image_size0"], entry["image_size1"])
            identity = _identity(len(points0))
            verified = _verify_pair(pair, conf, seed, points0, points1, identity, match_scores, sizes)
            match_seconds = float(entry["attr:match_seconds"]) + merge_seconds
            arrays = {"points0": points0, "points1": points1, "match_scores": match_scores.astype(np.float32)}
            _store_verified(writer, keys[pair], arrays, verified, match_seconds, merged_over=merged_over)
