"""The one way through: extract once per unique image -> match each pair -> verify ->
per-pair table (``<output_dir>/<method>/pairs.csv``) -> results (``results.csv``).

Every stage reads and writes crash-safe stores (``store.py``), so a rerun resumes
where an interrupted run stopped and evaluation reads only what runs wrote.
"""

from __future__ import annotations

import datetime as _dt
import json
import os
import platform
import threading
import time
import zlib
from collections import Counter, OrderedDict
from concurrent.futures import Future, ThreadPoolExecutor
from functools import lru_cache
from pathlib import Path
from typing import Any, Callable, Iterable, Iterator, TypeVar

import cv2
import numpy as np
import pandas as pd
import torch
from tqdm import tqdm

from . import methods as method_registry
from . import weights
from .extractors import build_extractor, resolve_device
from .images import ImageReadError, load_for_extraction, to_original_pixels
from .io_utils import atomic_write_csv, atomic_write_json
from .matchers import build_matcher
from .metrics import evaluate_scores
from .sequences import Sequence
from .store import ShardedStore
from .verify import verify_matches

T = TypeVar("T")
R = TypeVar("R")

PAIRS_COLUMNS = [
    "pair_index", "query", "reference", "label", "method", "profile",
    "num_keypoints_query", "num_keypoints_reference", "num_matches", "num_matches_filtered",
    "num_inliers", "score", "extract_seconds", "match_seconds", "verify_seconds",
]


def configure_threads(n_threads: int | None = None) -> int:
    """Set torch's and OpenCV's thread count: ``n_threads``, else $GVBENCH_THREADS, else
    every core. On a machine shared with other work, fewer threads than cores can be
    much faster (small matrix products then wait on busy cores); scores do not change."""
    n = n_threads or int(os.environ.get("GVBENCH_THREADS") or 0) or os.cpu_count() or 1
    torch.set_num_threads(n)
    cv2.setNumThreads(n)
    return n


def worker_count(workers: int | None = None) -> int:
    """How many images are extracted, and pairs matched and verified, at once:
    ``workers``, else $GVBENCH_WORKERS, else 1.

    With 1, one image (decoded ahead) and one pair (verified while the next is matched)
    are in flight, so the per-image and per-pair timers are close to each item's own
    cost, which the runtime analyses report. With 2 on a 2-core CPU, throughput rises
    (measured by ``bench``) but the timers include waiting for the shared cores. Scores
    are the same either way.
    """
    n = workers if workers is not None else int(os.environ.get("GVBENCH_WORKERS") or 1)
    if n < 1:
        raise ValueError(f"workers must be at least 1, got {n} (argument or $GVBENCH_WORKERS)")
    return n


def prefetch(items: Iterable[T], load: Callable[[T], R], depth: int = 4, workers: int = 2
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
    return ShardedStore(Path(cache_dir) / "features" / f"{extractor_conf['name']}-{method_registry.conf_hash(extractor_conf)}")


def image_key(image_root: Path, name: str) -> str:
    # Keyed by the resolved path: sequences sharing images share cache entries.
    return str((Path(image_root) / name).resolve())


def first_pair_using(sequence: Sequence, name: str) -> str:
    """'pair N: query reference' of the first pair that uses image ``name`` (for errors)."""
    index, pair = next((i, p) for i, p in enumerate(sequence.pairs) if name in (p.query, p.reference))
    return f"pair {index}: {pair.query} {pair.reference}"


def stored_features(features: dict[str, np.ndarray], image: np.ndarray, scale: float) -> dict[str, np.ndarray]:
    """What the cache holds for one image: keypoints in original pixels, scores,
    descriptors and the original (width, height)."""
    return {
        "keypoints": to_original_pixels(features["keypoints"], scale),
        "scores": features["scores"],
        "descriptors": features["descriptors"],
        "image_size": np.round(np.array(image.shape[1::-1]) * scale).astype(np.int64),
    }


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
    wanted = {image_key(sequence.image_root, name): name for name in (sequence.images if images is None else images)}
    todo = [key for key in wanted if key not in store]
    counts = {"images": len(wanted), "cached": len(wanted) - len(todo), "extracted": 0}
    if not todo:
        return counts
    extractor = build_extractor(extractor_conf, resolve_device(device))

    def load(key: str) -> tuple[np.ndarray, float]:
        try:
            return load_for_extraction(key, extractor_conf)
        except Exception as error:  # whatever decoding raised, it is this image's fault
            if isinstance(error, ImageReadError):
                raise
            raise ImageReadError(str(error)) from error

    def extract(loaded: tuple[np.ndarray, float]) -> tuple[dict[str, np.ndarray], float]:
        image, scale = loaded
        start = time.perf_counter()
        features = extractor(image)
        return stored_features(features, image, scale), time.perf_counter() - start

    workers = worker_count(workers)
    # One worker: decoding runs ahead in threads while this thread extracts. Several:
    # each worker decodes and extracts its own image (OpenCV and torch release the GIL).
    # Either way results come back in order and only this thread writes the store.
    if workers == 1:
        results: Iterable[tuple[str, Any]] = (
            (key, loaded if isinstance(loaded, BaseException) else extract(loaded))
            for key, loaded in prefetch(todo, load))
    else:
        results = prefetch(todo, lambda key: extract(load(key)), depth=2 * workers, workers=workers)
    bar = tqdm(total=len(todo), desc=f"extract {extractor_conf['name']}", disable=not progress, unit="img")
    with store.writer(flush_every) as writer:
        for key, extracted in results:
            if isinstance(extracted, ImageReadError):
                raise ImageReadError(f"{extracted} (image {wanted[key]!r} of sequence {sequence.name!r}, "
                                     f"{first_pair_using(sequence, wanted[key])})") from extracted
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


def pair_key(query: str, reference: str) -> str:
    return f"{query}\t{reference}"


def pair_seed(seed: int, query: str, reference: str) -> int:
    """RANSAC seed of one pair: the same whatever order or shard the pair runs in."""
    return zlib.crc32(f"{seed}\t{query}\t{reference}".encode()) & 0x7FFFFFFF


def method_dir(output_dir: Path, method: str) -> Path:
    return Path(output_dir) / method


def match_store(output_dir: Path, conf: dict[str, Any]) -> ShardedStore:
    """Per-pair matches and inlier masks of one method conf (a changed conf starts afresh)."""
    matching_conf = {k: conf[k] for k in ("extractor", "matcher", "verifier")}
    return ShardedStore(method_dir(output_dir, conf["method"]) / f"matches-{method_registry.conf_hash(matching_conf)}")


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
    todo = [p for p in sequence.pairs if pair_key(p.query, p.reference) not in matches]
    counts = {"pairs": len(sequence.pairs), "cached": len(sequence.pairs) - len(todo), "matched": 0}
    if not todo:
        return counts
    matcher = build_matcher(conf["matcher"], resolve_device(device))
    if conf["extractor"] is None:
        _match_dense_pairs(sequence, todo, conf, matcher, matches, seed, progress, flush_every)
        counts["matched"] = len(todo)
        return counts
    features = feature_store(cache_dir, conf["extractor"])
    reading = threading.Lock()  # one HDF5 reader at a time (h5py serialises anyway; the handle cache is not thread-safe)

    @lru_cache(maxsize=256)  # a query's candidates are consecutive; references recur
    def load(name: str) -> dict[str, np.ndarray]:
        key = image_key(sequence.image_root, name)
        with reading:
            if key not in features:
                raise KeyError(f"features of {name!r} are not in the cache {features.folder}; run extraction first")
            return features.read(key)

    # A matcher whose per-image work can be done once per image (LightGlue on a CPU:
    # models/lightglue_prepared.py) gets each image's state from a memory-bounded cache;
    # the first pair using an image is charged for preparing it.
    prepared = PreparedCache(matcher.prepare) if getattr(matcher, "can_prepare", False) else None

    def match_pair(pair: Any) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray], np.ndarray, np.ndarray, float]:
        features0, features1 = load(pair.query), load(pair.reference)
        start = time.perf_counter()
        if prepared is not None:
            pair_matches, match_scores = matcher.match_prepared(prepared.get(pair.query, features0),
                                                                prepared.get(pair.reference, features1))
        else:
            pair_matches, match_scores = matcher(features0, features1)
        return features0, features1, pair_matches, match_scores, time.perf_counter() - start

    def match_and_verify_pair(pair: Any) -> tuple[np.ndarray, np.ndarray, dict[str, Any], float, float]:
        features0, features1, pair_matches, match_scores, match_seconds = match_pair(pair)
        verified, verify_seconds = _verify_pair(pair, conf, seed, features0["keypoints"], features1["keypoints"],
                                                pair_matches, match_scores, image_sizes(features0, features1))
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
                _verify_and_store(writer, pair, conf, seed, features0["keypoints"], features1["keypoints"],
                                  pair_matches, match_scores, {"matches": pair_matches.astype(np.int32)},
                                  match_seconds, image_sizes(features0, features1))
                counts["matched"] += 1
                bar.update()
        else:
            # Several pairs at once, each matched then verified in its own thread; results
            # come back in order and are written from this thread only.
            for pair, done in prefetch(todo, match_and_verify_pair, depth=2 * workers, workers=workers):
                if isinstance(done, BaseException):
                    raise done
                pair_matches, match_scores, verified, match_seconds, verify_seconds = done
                _store_verified(writer, pair, pair_matches, match_scores, verified,
                                {"matches": pair_matches.astype(np.int32)}, match_seconds, verify_seconds)
                counts["matched"] += 1
                bar.update()
    bar.close()
    return counts


def image_sizes(features0: dict[str, np.ndarray], features1: dict[str, np.ndarray]) -> tuple[Any, Any]:
    """Original (width, height) of both images of a pair, from their cached features."""
    return features0.get("image_size"), features1.get("image_size")


def _verify_and_store(writer: Any, pair: Any, conf: dict[str, Any], seed: int, keypoints0: np.ndarray,
                      keypoints1: np.ndarray, pair_matches: np.ndarray, match_scores: np.ndarray,
                      arrays: dict[str, np.ndarray], match_seconds: float,
                      sizes: tuple[Any, Any] = (None, None)) -> None:
    """Verify one matched pair and commit its matches, inlier mask, counts and timings."""
    verified, verify_seconds = _verify_pair(pair, conf, seed, keypoints0, keypoints1, pair_matches, match_scores,
                                            sizes)
    _store_verified(writer, pair, pair_matches, match_scores, verified, arrays, match_seconds, verify_seconds)


def _verify_pair(pair: Any, conf: dict[str, Any], seed: int, keypoints0: np.ndarray, keypoints1: np.ndarray,
                 pair_matches: np.ndarray, match_scores: np.ndarray,
                 sizes: tuple[Any, Any] = (None, None)) -> tuple[dict[str, Any], float]:
    """RANSAC on one pair's matches, seeded by the pair: the verdict and its seconds."""
    start = time.perf_counter()
    verified = verify_matches(keypoints0, keypoints1, pair_matches, match_scores, conf["verifier"],
                              seed=pair_seed(seed, pair.query, pair.reference), image_sizes=sizes)
    return verified, time.perf_counter() - start


def _store_verified(writer: Any, pair: Any, pair_matches: np.ndarray, match_scores: np.ndarray,
                    verified: dict[str, Any], arrays: dict[str, np.ndarray], match_seconds: float,
                    verify_seconds: float) -> None:
    """Commit one verified pair: its matches, inlier mask, counts and timings."""
    writer.put(
        pair_key(pair.query, pair.reference),
        {**arrays, "match_scores": match_scores.astype(np.float32), "inlier_mask": verified["inlier_mask"]},
        {"num_matches": verified["num_matches"], "num_matches_filtered": verified["num_matches_filtered"],
         "num_inliers": verified["num_inliers"], "match_seconds": match_seconds, "verify_seconds": verify_seconds},
    )


def _match_dense_pairs(sequence: Sequence, todo: list, conf: dict[str, Any], matcher: Callable, matches: ShardedStore,
                       seed: int, progress: bool, flush_every: int) -> None:
    """Dense matchers (LoFTR) see both images of every pair: no per-image cache.
    Decoding overlaps compute through the same prefetching loader."""
    def load_pair(pair: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        image0, scale0 = load_for_extraction(sequence.image_root / pair.query, conf["matcher"])
        image1, scale1 = load_for_extraction(sequence.image_root / pair.reference, conf["matcher"])
        return image0, scale0, image1, scale1

    bar = tqdm(total=len(todo), desc=f"match {conf['method']}", disable=not progress, unit="pair")
    with matches.writer(flush_every) as writer:
        for pair, loaded in prefetch(todo, load_pair):
            if isinstance(loaded, BaseException):
                raise ImageReadError(f"{loaded} (pair {pair.query} {pair.reference} of {sequence.name!r})") from loaded
            image0, scale0, image1, scale1 = loaded
            start = time.perf_counter()
            points0, points1, match_scores = matcher(image0, image1)
            points0, points1 = to_original_pixels(points0, scale0), to_original_pixels(points1, scale1)
            match_seconds = time.perf_counter() - start
            identity = np.repeat(np.arange(len(points0))[:, None], 2, axis=1)
            sizes = (np.round(np.array(image0.shape[1::-1]) * scale0), np.round(np.array(image1.shape[1::-1]) * scale1))
            _verify_and_store(writer, pair, conf, seed, points0, points1, identity, match_scores,
                              {"points0": points0, "points1": points1}, match_seconds, sizes)
            bar.update()
    bar.close()


def pairs_table(sequence: Sequence, conf: dict[str, Any], cache_dir: Path, output_dir: Path) -> pd.DataFrame:
    """The per-pair table of a finished run, built only from the stores."""
    matches = match_store(output_dir, conf)
    matches.refresh()
    dense = conf["extractor"] is None
    uses = Counter(name for pair in sequence.pairs for name in (pair.query, pair.reference))
    image_info: dict[str, tuple[int, float]] = {}
    if not dense:
        features = feature_store(cache_dir, conf["extractor"])
        features.refresh()
        for name in uses:
            entry = features.read(image_key(sequence.image_root, name), fields=("keypoints",))  # not descriptors
            image_info[name] = (len(entry["keypoints"]), float(entry["attr:seconds"]))
        features.close()
    rows = []
    for index, pair in enumerate(sequence.pairs):
        entry = matches.read(pair_key(pair.query, pair.reference), fields=())  # the counts and timers only
        if dense:  # a dense matcher's keypoints are its matches; its whole cost is matching
            keypoints_query = keypoints_reference = int(entry["attr:num_matches"])
            extract_seconds = 0.0
        else:
            keypoints_query, keypoints_reference = image_info[pair.query][0], image_info[pair.reference][0]
            # Extraction is amortised: each image's time is shared among the pairs that use it.
            extract_seconds = sum(image_info[n][1] / uses[n] for n in (pair.query, pair.reference))
        rows.append({
            "pair_index": index, "query": pair.query, "reference": pair.reference, "label": pair.label,
            "method": conf["method"], "profile": conf["profile"],
            "num_keypoints_query": keypoints_query, "num_keypoints_reference": keypoints_reference,
            "num_matches": int(entry["attr:num_matches"]), "num_matches_filtered": int(entry["attr:num_matches_filtered"]),
            "num_inliers": int(entry["attr:num_inliers"]), "score": int(entry["attr:num_inliers"]),
            "extract_seconds": extract_seconds, "match_seconds": float(entry["attr:match_seconds"]),
            "verify_seconds": float(entry["attr:verify_seconds"]),
        })
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


def environment_info(device: torch.device) -> dict[str, Any]:
    import kornia

    info = {
        "device": str(device),
        "device_name": torch.cuda.get_device_name(device) if device.type == "cuda" else cpu_name(),
        "cpu_count": os.cpu_count(),
        "torch": torch.__version__, "kornia": kornia.__version__, "opencv": cv2.__version__,
        "numpy": np.__version__, "python": platform.python_version(), "platform": platform.platform(),
    }
    return info


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
) -> pd.DataFrame:
    """Run one method on a sequence end to end; writes ``pairs.csv`` and ``run.json``.
    ``workers`` images or pairs run at once (``worker_count``: default $GVBENCH_WORKERS or 1).

    Missing weights fail here, before any work. Finished work found in the caches is
    reused, so an interrupted run resumes.
    """
    conf = method_registry.resolve_method(method, profile)
    weights.require(*method_registry.required_checkpoints(method, profile))
    resolved_device = resolve_device(device)
    configure_threads(threads)
    folder = method_dir(output_dir, method)
    # A failed or killed run must not leave the previous run's pairs.csv looking like its result.
    for stale in ("pairs.csv", "run.json"):
        (folder / stale).unlink(missing_ok=True)
    started = time.perf_counter()
    workers = worker_count(workers)
    extraction = (extract_features(sequence, conf["extractor"], cache_dir, resolved_device, progress, workers=workers)
                  if conf["extractor"] else {"images": 0, "cached": 0, "extracted": 0})
    extracted = time.perf_counter()
    matching = match_and_verify(sequence, conf, cache_dir, output_dir, resolved_device, seed, progress, workers=workers)
    finished = time.perf_counter()
    table = pairs_table(sequence, conf, cache_dir, output_dir)
    # pairs.csv is written last: its presence marks a finished run (methods_with_results).
    atomic_write_json(folder / "run.json", {
        "sequence": sequence.name, "image_root": str(sequence.image_root), "n_pairs": len(sequence.pairs),
        "conf": conf, "seed": seed, "environment": environment_info(resolved_device),
        "this_run": {"extraction": extraction, "matching": matching, "workers": workers,
                     "extract_wall_seconds": extracted - started, "match_verify_wall_seconds": finished - extracted},
        "finished_at": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
    })
    atomic_write_csv(folder / "pairs.csv", table)
    return table


# ------------------------------------------------------------------- evaluation --
def load_pairs_table(output_dir: Path, method: str) -> pd.DataFrame:
    path = method_dir(output_dir, method) / "pairs.csv"
    if not path.is_file():
        raise FileNotFoundError(f"no results for method {method!r}: {path} is missing; run the method first")
    return pd.read_csv(path, keep_default_na=False)


def methods_with_results(output_dir: Path) -> list[str]:
    """Methods that have a finished ``pairs.csv``, in registry order, then any others."""
    found = {p.parent.name for p in Path(output_dir).glob("*/pairs.csv")}
    ordered = [m for m in method_registry.METHODS if m in found]
    return ordered + sorted(found - set(ordered))


def evaluate(output_dir: Path, methods: list[str] | None = None, write: bool = True) -> pd.DataFrame:
    """AP, MR and seconds per pair for every method with results; writes ``results.csv``."""
    output_dir = Path(output_dir)
    methods = methods or methods_with_results(output_dir)
    if not methods:
        raise FileNotFoundError(f"no method results under {output_dir}: run a method first")
    rows = []
    for method in methods:
        table = load_pairs_table(output_dir, method)
        run = json.loads((method_dir(output_dir, method) / "run.json").read_text())
        metrics = evaluate_scores(table["label"].to_numpy(), table["score"].to_numpy(),
                                  where=f"{method_dir(output_dir, method) / 'pairs.csv'}")
        rows.append({
            "sequence": run["sequence"], "method": method, "paper_name": run["conf"]["paper_name"],
            "profile": run["conf"]["profile"], **metrics,
            "extract_seconds_per_pair": table["extract_seconds"].mean(),
            "match_seconds_per_pair": table["match_seconds"].mean(),
            "verify_seconds_per_pair": table["verify_seconds"].mean(),
            "seconds_per_pair": (table["extract_seconds"] + table["match_seconds"] + table["verify_seconds"]).mean(),
            "device": run["environment"]["device"],
            # >1: the seconds above include waiting for cores shared by concurrent images/pairs
            "workers": run.get("this_run", {}).get("workers", 1),  # runs written before workers existed: 1
        })
    results = pd.DataFrame(rows)
    if write:
        atomic_write_csv(output_dir / "results.csv", results)
    return results
