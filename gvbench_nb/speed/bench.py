"""Throughput, measured: our pipeline against a per-pair reference pipeline.

GV-Bench's own code loads and extracts BOTH images of every pair, one pair at a
time. Ours extracts each unique image once into a cache, then matches and verifies
every pair from it (and, for LightGlue on a CPU, also the part of the matcher that sees
one image only: ``matching/lightglue_prepared.py``, bit-identical to kornia's forward).
``bench`` runs both on the same pairs in one process, with the same extractor, matcher
and verifier models, checks that every pair gets the same ``num_inliers`` (RANSAC is
seeded per pair, so they must) and writes:

* ``<bench_dir>/<sequence>_<method>.csv``: one row per repeat and pipeline;
* ``<bench_dir>/summary.csv``: one row per (sequence, method, profile, n_pairs), medians
  over the repeats and the speed-up (median of the per-repeat ratios);
* ``<bench_dir>/scaling_<sequence>_<method>.csv``: cost against pairs and unique images;
* optionally the prefetch-overlap measurement and a cProfile report.

``python -m gvbench_nb.speed --estimate`` turns the summary into an estimate of the six
official sequences from their pair lists. Every number comes from a measurement
written by this module; none is typed in.
"""

from __future__ import annotations

import argparse
import cProfile
import datetime as _dt
import io
import os
import pstats
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

import cv2
import numpy as np
import pandas as pd
from tqdm import tqdm

from gvbench_nb import methods as method_registry
from gvbench_nb.data.sequences import Sequence, read_pairs
from gvbench_nb.io_utils import atomic_write_csv
from gvbench_nb.protocol.images import load_for_extraction, to_original_pixels
from gvbench_nb.protocol.ransac import verify_matches
from gvbench_nb.runner import concurrency, image_features, method_runs, pair_matching, scoring
from gvbench_nb.runner.jobs import add_jobs_argument

if TYPE_CHECKING:
    import torch

PROJECT_ROOT = Path(__file__).resolve().parents[2]
DEFAULT_BENCH_DIR = PROJECT_ROOT / "outputs" / "bench"
DEFAULT_SCALING_LIMITS = (50, 100, 200, 400)
# Ours runs two jobs (images or pairs at a time) when benched: on two cores that used them
# better than one model call with two threads for sift-nn (README); for LightGlue not consistently.
DEFAULT_BENCH_JOBS = 2
# The speed-up over the per-pair pipeline this package is built to reach on a CPU, per method.
SPEEDUP_TARGETS: dict[str, float] = {"sift-nn": 5.0, "disk-lg": 3.0}
OFFICIAL_SEQUENCES = ("day", "night", "nordland", "season", "uacampus", "weather")
CACHED, PER_PAIR = "cached", "per_pair"  # the two pipelines, as named in every CSV
STAGES = ("extract", "match", "verify", "other")
# Timer sums per stage, and the wall time of matching + verification (they overlap in ours).
TIMED = STAGES + ("match_verify_wall",)
GPU_NOTE = "These figures are this CPU's. On a machine with a CUDA GPU, `bench` (device auto or cuda) measures the GPU."


class ScoreMismatchError(AssertionError):
    """The cached and the per-pair pipeline disagree on a pair's score: the cache is wrong."""


# ------------------------------------------------------------------ environment --
def environment_row(device: torch.device) -> dict[str, Any]:
    """What a timing depends on: device, threads, cores, load, when."""
    import torch

    load_1m, load_5m, _ = os.getloadavg()
    return {
        "device": str(device),
        "device_name": (
            torch.cuda.get_device_name(device)
            if device.type == "cuda"
            else concurrency.environment_info(device)["device_name"]
        ),
        "torch_threads": torch.get_num_threads(),
        "opencv_threads": cv2.getNumThreads(),
        "cpu_count": os.cpu_count(),
        "loadavg_1m": round(load_1m, 2),
        "loadavg_5m": round(load_5m, 2),
        "date": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
    }


# ------------------------------------------------------------------- pipelines --
def run_cached_pipeline(
    sequence: Sequence,
    conf: dict[str, Any],
    work_dir: Path,
    device: torch.device,
    seed: int = 0,
    workers: int | None = None,
) -> tuple[pd.DataFrame, dict[str, float]]:
    """Our pipeline from a cold cache in ``work_dir``, ``workers`` images or pairs at a
    time (``concurrency.worker_count``): per-pair table and stage seconds (totals).

    ``extract`` is the wall time of extraction (decoding overlapped by the prefetcher);
    ``match``/``verify`` are the per-pair timers' sums, which overlap (matching runs a pair
    ahead of verification), so ``match_verify_wall`` is their stage's wall time; ``other``
    is the rest (writing stores, building the table).
    """
    cache_dir, output_dir = Path(work_dir) / "cache", Path(work_dir) / "out"
    start = time.perf_counter()
    if not method_registry.is_dense(conf):
        image_features.extract_features(sequence, conf["extractor"], cache_dir, device, progress=False, workers=workers)
    extracted = time.perf_counter()
    pair_matching.match_and_verify(sequence, conf, cache_dir, output_dir, device, seed, progress=False, workers=workers)
    matched = time.perf_counter()
    table = method_runs.pairs_table(sequence, conf, cache_dir, output_dir, seed)
    wall = time.perf_counter() - start
    match, verify = float(table["match_seconds"].sum()), float(table["verify_seconds"].sum())
    seconds = {
        "wall": wall,
        "extract": extracted - start,
        "match": match,
        "verify": verify,
        "match_verify_wall": matched - extracted,
    }
    seconds["other"] = wall - seconds["extract"] - seconds["match_verify_wall"]
    return table[["query", "reference", "num_matches", "num_inliers"]], seconds


def _extract_image(path: Path, extractor_conf: dict[str, Any], extractor: Callable) -> dict[str, np.ndarray]:
    """One image's features exactly as ``image_features.extract_features`` stores them."""
    image, scale = load_for_extraction(path, extractor_conf)
    return image_features.stored_features(extractor(image), image, scale, extractor_conf.get("store_float16", False))


def _dense_pair(
    root: Path, pair: Any, matcher_conf: dict[str, Any], matcher: Callable
) -> tuple[np.ndarray, np.ndarray, np.ndarray, tuple[np.ndarray, np.ndarray]]:
    """Matched points in original pixels, their scores and both images' original (width, height)."""
    image0, scale0 = load_for_extraction(root / pair.query, matcher_conf)
    image1, scale1 = load_for_extraction(root / pair.reference, matcher_conf)
    points0, points1, scores = matcher(image0, image1)
    sizes = (np.round(np.array(image0.shape[1::-1]) * scale0), np.round(np.array(image1.shape[1::-1]) * scale1))
    return to_original_pixels(points0, scale0), to_original_pixels(points1, scale1), scores, sizes


def run_per_pair_pipeline(
    sequence: Sequence, conf: dict[str, Any], device: torch.device, seed: int = 0, progress: bool = False
) -> tuple[pd.DataFrame, dict[str, float]]:
    """GV-Bench's way: for every pair, load and extract both images, then match and verify.

    Same extractor, matcher and verifier models (and seeds) as ours; no cache, no
    prefetching; the matcher's plain two-image call for every pair. ``extract`` includes
    decoding (the reference does it inline); model construction is in ``other``.
    """
    from gvbench_nb.protocol.features import build_extractor
    from gvbench_nb.protocol.matching import build_matcher

    start = time.perf_counter()
    dense = method_registry.is_dense(conf)
    extractor = None if dense else build_extractor(conf["extractor"], device)
    matcher = build_matcher(conf["matcher"], device)
    seconds = {"extract": 0.0, "match": 0.0, "verify": 0.0}
    rows = []
    for pair in tqdm(sequence.pairs, desc=f"per-pair {conf['method']}", disable=not progress, unit="pair"):
        began = time.perf_counter()
        if dense:
            points0, points1, match_scores, sizes = _dense_pair(sequence.image_root, pair, conf["matcher"], matcher)
            matches = np.repeat(np.arange(len(points0))[:, None], 2, axis=1)
            extracted = began  # a dense matcher's whole cost is matching
        else:
            assert extractor is not None, "a sparse method has an extractor"
            features0 = _extract_image(sequence.image_root / pair.query, conf["extractor"], extractor)
            features1 = _extract_image(sequence.image_root / pair.reference, conf["extractor"], extractor)
            extracted = time.perf_counter()
            matches, match_scores = matcher(features0, features1)
            points0, points1 = features0["keypoints"], features1["keypoints"]
            sizes = pair_matching.image_sizes(features0, features1)
        matched = time.perf_counter()
        verified = verify_matches(
            points0,
            points1,
            matches,
            match_scores,
            conf["verifier"],
            seed=pair_matching.pair_seed(seed, pair.query, pair.reference),
            image_sizes=sizes,
        )
        done = time.perf_counter()
        seconds["extract"] += extracted - began
        seconds["match"] += matched - extracted
        seconds["verify"] += done - matched
        rows.append(
            {
                "query": pair.query,
                "reference": pair.reference,
                "num_matches": verified["num_matches"],
                "num_inliers": verified["num_inliers"],
            }
        )
    seconds["wall"] = time.perf_counter() - start
    seconds["match_verify_wall"] = seconds["match"] + seconds["verify"]  # one after the other
    seconds["other"] = seconds["wall"] - seconds["extract"] - seconds["match_verify_wall"]
    return pd.DataFrame(rows), seconds


def check_same_scores(cached: pd.DataFrame, per_pair: pd.DataFrame, where: str) -> None:
    """Raise ``ScoreMismatchError`` naming the pairs whose num_inliers differ."""
    if (
        len(cached) != len(per_pair)
        or not (cached[["query", "reference"]].values == per_pair[["query", "reference"]].values).all()
    ):
        raise ScoreMismatchError(f"{where}: the two pipelines ran different pairs ({len(cached)} vs {len(per_pair)})")
    differ = np.nonzero(cached["num_inliers"].to_numpy() != per_pair["num_inliers"].to_numpy())[0]
    if len(differ):
        shown = "\n".join(
            f"  pair {i}: {cached['query'].iat[i]} {cached['reference'].iat[i]}: cached "
            f"{cached['num_inliers'].iat[i]} inliers ({cached['num_matches'].iat[i]} matches), per-pair "
            f"{per_pair['num_inliers'].iat[i]} ({per_pair['num_matches'].iat[i]} matches)"
            for i in differ[:10]
        )
        raise ScoreMismatchError(
            f"{where}: SCORES DIFFER on {len(differ)} of {len(cached)} pairs between the cached pipeline and "
            f"the per-pair reference:\n{shown}\nThe cache must reproduce fresh extraction exactly: check what "
            "extract_features stores (dtype, keypoint scaling, image_size) against bench._extract_image."
        )


# ------------------------------------------------------------------- the bench --
def bench_method(
    sequence: Sequence,
    method: str,
    profile: str,
    repeats: int = 3,
    device: str = "auto",
    seed: int = 0,
    progress: bool = True,
    workers: int = DEFAULT_BENCH_JOBS,
) -> pd.DataFrame:
    """Both pipelines ``repeats`` times on ``sequence``; one row per (repeat, pipeline).
    Ours runs ``workers`` images or pairs at a time; the per-pair pipeline, as the
    reference code, one pair at a time.

    The order alternates between repeats so neither pipeline always runs on a warm
    page cache or a quieter machine. Raises ``ScoreMismatchError`` on any difference.
    """
    from gvbench_nb.protocol.features.base import resolve_device

    conf = method_registry.resolve_method(method, profile)
    resolved = resolve_device(device)
    rows = []
    for repeat in tqdm(range(repeats), desc=f"bench {method}", disable=not progress, unit="repeat"):
        order = (CACHED, PER_PAIR) if repeat % 2 == 0 else (PER_PAIR, CACHED)
        results: dict[str, pd.DataFrame] = {}
        for which in order:
            environment = environment_row(resolved)
            if which == CACHED:
                with tempfile.TemporaryDirectory(prefix="gvbench-bench-") as work_dir:
                    results[which], seconds = run_cached_pipeline(
                        sequence, conf, Path(work_dir), resolved, seed, workers
                    )
            else:
                results[which], seconds = run_per_pair_pipeline(sequence, conf, resolved, seed)
            rows.append(
                _timing_row(
                    sequence,
                    conf,
                    repeat,
                    which,
                    seconds,
                    {"workers": workers if which == CACHED else 1, **environment},
                )
            )
        check_same_scores(results[CACHED], results[PER_PAIR], f"{sequence.name} {method} ({profile}), repeat {repeat}")
    return pd.DataFrame(rows)


def _timing_row(
    sequence: Sequence,
    conf: dict[str, Any],
    repeat: int,
    which: str,
    seconds: dict[str, float],
    environment: dict[str, Any],
) -> dict[str, Any]:
    n_pairs = len(sequence.pairs)
    return {
        "sequence": sequence.name,
        "method": conf["method"],
        "profile": conf["profile"],
        "n_pairs": n_pairs,
        "n_images": len(sequence.images),
        "repeat": repeat,
        "pipeline": which,
        "wall_seconds": seconds["wall"],
        "pairs_per_second": n_pairs / seconds["wall"],
        **{f"{stage}_seconds_per_pair": seconds[stage] / n_pairs for stage in TIMED},
        **environment,
    }


def summarize_bench(rows: pd.DataFrame) -> pd.DataFrame:
    """One row per (sequence, method, profile, n_pairs): medians over repeats and the speed-up."""
    summaries = []
    keys = ["sequence", "method", "profile", "n_pairs"]
    for key, group in rows.groupby(keys, sort=False):
        cached = group[group["pipeline"] == CACHED].set_index("repeat")
        per_pair = group[group["pipeline"] == PER_PAIR].set_index("repeat")
        ratios = cached["pairs_per_second"] / per_pair["pairs_per_second"]
        # Amdahl's bound: caching removes repeated extraction only. With extraction free but
        # pairs matched and verified one at a time, as the per-pair pipeline does, this is
        # the speed-up; beyond it only by matching faster (ours: several pairs at once, and
        # LightGlue's per-image part done once per image on a CPU).
        ceilings = 1.0 / (per_pair["pairs_per_second"] * per_pair["match_verify_wall_seconds_per_pair"])
        n_images = int(group["n_images"].iat[0])
        row: dict[str, Any] = dict(zip(keys, key))
        row.update(
            {
                "n_images": n_images,
                "uses_per_image": 2 * row["n_pairs"] / n_images,
                "repeats": len(ratios),
                "cached_pairs_per_second": cached["pairs_per_second"].median(),
                "per_pair_pairs_per_second": per_pair["pairs_per_second"].median(),
                "speedup": ratios.median(),
                "speedup_min": ratios.min(),
                "speedup_max": ratios.max(),
                "speedup_target": SPEEDUP_TARGETS.get(row["method"], np.nan),
                "speedup_if_extraction_were_free": ceilings.median(),
            }
        )
        row["meets_target"] = bool(row["speedup"] >= row["speedup_target"]) if row["method"] in SPEEDUP_TARGETS else ""
        for name, frame in ((CACHED, cached), (PER_PAIR, per_pair)):
            for stage in TIMED:
                row[f"{name}_{stage}_seconds_per_pair"] = frame[f"{stage}_seconds_per_pair"].median()
        # Per unique image: what extraction costs when each image is extracted once (for estimates).
        row["cached_extract_seconds_per_image"] = row[f"{CACHED}_extract_seconds_per_pair"] * row["n_pairs"] / n_images
        row["scores_identical"] = True  # bench_method raised otherwise
        first, last = group.iloc[0], group.iloc[-1]
        row.update(
            {
                "loadavg_1m_start": first["loadavg_1m"],
                "loadavg_1m_end": last["loadavg_1m"],
                "loadavg_1m_max": group["loadavg_1m"].max(),
                **{c: first[c] for c in ("device", "device_name", "torch_threads", "opencv_threads", "cpu_count")},
                "cached_workers": int(cached["workers"].iat[0]) if "workers" in cached else 1,
                "date": first["date"],
            }
        )
        summaries.append(row)
    return pd.DataFrame(summaries)


def _merge_csv(path: Path, new: pd.DataFrame, keys: list[str]) -> pd.DataFrame:
    """Replace the rows of ``path`` that share ``keys`` with ``new`` (other runs stay)."""
    if path.is_file():
        old = pd.read_csv(path, keep_default_na=False)
        if set(keys) <= set(old.columns):
            stale = old[keys].astype(str).agg("\t".join, axis=1).isin(new[keys].astype(str).agg("\t".join, axis=1))
            new = pd.concat([old[~stale], new], ignore_index=True)
    atomic_write_csv(path, new)
    return new


def print_summary(summary: pd.DataFrame) -> None:
    for _, row in summary.iterrows():
        target = (
            f" (target >= {row['speedup_target']:g}x: {'met' if row['meets_target'] else 'NOT met'})"
            if row["method"] in SPEEDUP_TARGETS
            else ""
        )
        print(
            f"\n{row['sequence']} {row['method']} ({row['profile']}), {row['n_pairs']} pairs over "
            f"{row['n_images']} unique images ({row['uses_per_image']:.2f} uses per image), "
            f"median of {row['repeats']} repeats, load average {row['loadavg_1m_start']}-{row['loadavg_1m_end']}:"
        )
        print(
            f"  ours: --jobs {row['cached_workers']} (images or pairs at a time); per-pair pipeline: one pair at a time"
        )
        print(
            f"  cached   {row['cached_pairs_per_second']:8.2f} pairs/s   "
            f"per-pair {row['per_pair_pairs_per_second']:8.2f} "
            f"pairs/s   speed-up {row['speedup']:.2f}x [{row['speedup_min']:.2f}-{row['speedup_max']:.2f}]{target}"
        )
        print("  seconds per pair   " + "  ".join(f"{s:>8}" for s in STAGES) + "  match+verify wall")
        for name in (CACHED, PER_PAIR):
            print(f"  {name:<17}" + "  ".join(f"{row[f'{name}_{s}_seconds_per_pair']:8.4f}" for s in TIMED))
        print("  (match and verify are timer sums; ours runs them overlapped, so its wall column is what they cost)")
        print(
            f"  speed-up if extraction were free and pairs were matched as the per-pair pipeline does "
            f"(Amdahl's bound on caching features): "
            f"{row['speedup_if_extraction_were_free']:.2f}x"
        )
        print("  scores identical on every pair: yes")


# --------------------------------------------------------------------- scaling --
def scaling_table(
    sequence: Sequence,
    method: str,
    profile: str,
    limits: tuple[int, ...] = DEFAULT_SCALING_LIMITS,
    device: str = "auto",
    seed: int = 0,
    per_pair_extract_per_image: float | None = None,
) -> pd.DataFrame:
    """Cost against the number of pairs and of unique images, from ONE cold run.

    The cached pipeline runs once on the first ``max(limits)`` pairs; every prefix's
    cost is then the sum of the measured per-image extraction and per-pair matching and
    verification times of the images and pairs it holds (per-run overhead excluded).
    ``per_pair_extract_seconds`` is what the per-pair pipeline would spend extracting
    (each pair's two images, extractor time only); ``per_pair_extract_seconds_with_decode``
    uses the bench's measured per-image cost of the per-pair pipeline, decode included,
    when given.
    """
    from gvbench_nb.protocol.features.base import resolve_device

    conf = method_registry.resolve_method(method, profile)
    largest = sequence.limited(max(limits))
    limits = tuple(sorted({min(limit, len(largest.pairs)) for limit in limits}))
    resolved = resolve_device(device)
    with tempfile.TemporaryDirectory(prefix="gvbench-scaling-") as work_dir:
        started = time.perf_counter()
        # one worker: the stage sums below need each image's and pair's own cost
        table, seconds = run_cached_pipeline(largest, conf, Path(work_dir), resolved, seed, workers=1)
        wall = time.perf_counter() - started
        image_seconds = (
            _image_seconds(largest, conf, Path(work_dir) / "cache")
            if conf["extractor"]
            else dict.fromkeys(largest.images, 0.0)
        )
        full = method_runs.pairs_table(largest, conf, Path(work_dir) / "cache", Path(work_dir) / "out", seed)
    environment = environment_row(resolved)
    rows = []
    for limit in limits:
        prefix = largest.limited(limit)
        pairs = full.iloc[:limit]
        extract = sum(image_seconds[name] for name in prefix.images)
        extract_per_pair = sum(image_seconds[p.query] + image_seconds[p.reference] for p in prefix.pairs)
        match, verify = float(pairs["match_seconds"].sum()), float(pairs["verify_seconds"].sum())
        row: dict[str, Any] = {
            "sequence": sequence.name,
            "method": method,
            "profile": profile,
            "n_pairs": limit,
            "n_images": len(prefix.images),
            "uses_per_image": 2 * limit / len(prefix.images),
            "extract_seconds": extract,
            "match_seconds": match,
            "verify_seconds": verify,
            "total_seconds": extract + match + verify,
            "seconds_per_pair": (extract + match + verify) / limit,
            "per_pair_extract_seconds": extract_per_pair,
            "per_pair_total_seconds": extract_per_pair + match + verify,
        }
        if per_pair_extract_per_image is not None:
            row["per_pair_extract_seconds_with_decode"] = 2 * limit * per_pair_extract_per_image
        row["speedup_from_stage_sums"] = row["per_pair_total_seconds"] / row["total_seconds"]
        rows.append(row)
    frame = pd.DataFrame(rows)
    frame["measured_wall_seconds_of_largest_run"] = wall  # everything, overheads included
    for key, value in environment.items():
        frame[key] = value
    return frame


def _image_seconds(sequence: Sequence, conf: dict[str, Any], cache_dir: Path) -> dict[str, float]:
    """Measured extractor seconds of each unique image (the cache's per-entry timer)."""
    store = image_features.feature_store(cache_dir, conf["extractor"])
    store.refresh()
    seconds = {
        name: float(store.read(image_features.image_key(sequence.image_root, name))["attr:seconds"])
        for name in sequence.images
    }
    store.close()
    return seconds


# ------------------------------------------------- prefetch overlap and profile --
def measure_prefetch_overlap(sequence: Sequence, method: str, profile: str, device: str = "auto") -> dict[str, Any]:
    """Does the prefetching loader hide decoding behind extraction? Three timings:

    decoding alone (sequential), extraction alone (on decoded images), and
    ``extract_features`` from a cold cache (prefetching, plus store writes). The share
    of decoding hidden is ``(decode + extract - extract_features) / decode`` (a lower
    bound: extract_features also writes the store).
    """
    from gvbench_nb.protocol.features import build_extractor
    from gvbench_nb.protocol.features.base import resolve_device

    conf = method_registry.resolve_method(method, profile)
    if method_registry.is_dense(conf):
        raise ValueError(f"{method} is a dense matcher: it has no per-image extraction to overlap")
    resolved = resolve_device(device)
    extractor_conf = conf["extractor"]
    paths = [sequence.image_root / name for name in sequence.images]
    extractor = build_extractor(extractor_conf, resolved)
    started = time.perf_counter()
    images = [load_for_extraction(path, extractor_conf)[0] for path in paths]
    decode = time.perf_counter() - started
    started = time.perf_counter()
    for image in images:
        extractor(image)
    extract = time.perf_counter() - started
    del images
    with tempfile.TemporaryDirectory(prefix="gvbench-overlap-") as work_dir:
        started = time.perf_counter()
        image_features.extract_features(sequence, extractor_conf, Path(work_dir), resolved, progress=False, workers=1)
        prefetched = time.perf_counter() - started
    return {
        "sequence": sequence.name,
        "method": method,
        "profile": profile,
        "n_images": len(paths),
        "decode_seconds": decode,
        "extract_seconds": extract,
        "sequential_seconds": decode + extract,
        "extract_features_seconds": prefetched,
        "decode_hidden_fraction": (decode + extract - prefetched) / decode if decode > 0 else np.nan,
        **environment_row(resolved),
    }


def profile_pipeline(
    sequence: Sequence, method: str, profile: str, device: str = "auto", seed: int = 0, top: int = 25
) -> str:
    """cProfile of our pipeline from a cold cache; the top functions by own and cumulative time."""
    from gvbench_nb.protocol.features.base import resolve_device

    conf = method_registry.resolve_method(method, profile)
    resolved = resolve_device(device)
    profiler = cProfile.Profile()
    with tempfile.TemporaryDirectory(prefix="gvbench-cprofile-") as work_dir:
        profiler.enable()
        run_cached_pipeline(sequence, conf, Path(work_dir), resolved, seed)
        profiler.disable()
    report = io.StringIO()
    report.write(
        f"cProfile: {sequence.name} {method} ({profile}), {len(sequence.pairs)} pairs, "
        f"{len(sequence.images)} images, cold cache\n"
    )
    for order in ("tottime", "cumulative"):
        report.write(f"\n===== top {top} by {order} =====\n")
        pstats.Stats(profiler, stream=report).strip_dirs().sort_stats(order).print_stats(top)
    return report.getvalue()


# ------------------------------------------------------------------- estimates --
def require_official_lists(gt_dir: Path) -> None:
    """The estimate counts the official sequences' pairs: their lists must be in ``gt_dir``."""
    from gvbench_nb.data.fetch import DataError

    missing = [name for name in OFFICIAL_SEQUENCES if not (Path(gt_dir) / f"{name}.txt").is_file()]
    if missing:
        raise DataError(
            f"bench --estimate needs the official pair lists, and {', '.join(f'{m}.txt' for m in missing)} "
            f"{'is' if len(missing) == 1 else 'are'} missing from {gt_dir}: run `python -m gvbench_nb data fetch gvbench-lists` "
            "(or set GVBENCH_DATA to the folder holding gvbench_gt/)"
        )


def official_sequence_sizes(gt_dir: Path) -> pd.DataFrame:
    """Pairs and unique images of each official sequence, counted from its pair list."""
    require_official_lists(gt_dir)
    rows = []
    for name in OFFICIAL_SEQUENCES:
        pairs = read_pairs(Path(gt_dir) / f"{name}.txt")
        images = {p for pair in pairs for p in (pair.query, pair.reference)}
        rows.append(
            {
                "sequence": name,
                "n_pairs": len(pairs),
                "n_images": len(images),
                "uses_per_image": 2 * len(pairs) / len(images),
            }
        )
    return pd.DataFrame(rows)


def costs_from_bench(summary: pd.DataFrame) -> pd.DataFrame:
    """Per (method, profile): measured seconds per unique image (extraction) and per pair
    (ours: matching and verification, overlapped, plus overhead; the per-pair pipeline:
    everything). From the largest bench run of each."""
    latest = summary.sort_values("n_pairs").groupby(["method", "profile"], sort=False).tail(1)
    rows = []
    for _, measured in latest.iterrows():
        # Summaries written before matching overlapped verification have no wall column.
        wall_column = f"{CACHED}_match_verify_wall_seconds_per_pair"
        stages = ("match_verify_wall", "other") if pd.notna(measured.get(wall_column)) else ("match", "verify", "other")
        rows.append(
            {
                "method": measured["method"],
                "profile": measured["profile"],
                "source": "bench",
                "extract_seconds_per_image": measured["cached_extract_seconds_per_image"],
                "cached_seconds_per_pair": sum(measured[f"{CACHED}_{s}_seconds_per_pair"] for s in stages),
                "per_pair_seconds_per_pair": 1.0 / measured["per_pair_pairs_per_second"],
                "measured_on": f"bench: {measured['sequence']} ({measured['n_pairs']} pairs), {measured['device_name']}, "
                f"{measured['cpu_count']} CPUs, load {measured['loadavg_1m_start']}",
            }
        )
    return pd.DataFrame(rows)


def costs_from_runs(output_dir: Path) -> pd.DataFrame:
    """The same costs from the per-pair timers of finished runs (``<output_dir>/<method>/pairs.csv``),
    for every method that ran. The per-pair pipeline is then estimated as two extractions
    and one match a pair (without decoding, which the bench measures)."""
    from gvbench_nb.evaluation.run_tables import load_run

    rows = []
    for method in scoring.methods_with_results(output_dir):
        table = scoring.load_pairs_table(output_dir, method)
        n_images = len(set(table["query"]) | set(table["reference"]))
        # A pair's extract_seconds is its images' times shared among their pairs: the sum is the total.
        per_image = float(table["extract_seconds"].sum()) / n_images
        per_pair = float((table["match_seconds"] + table["verify_seconds"]).mean())
        run = load_run(output_dir, method)
        rows.append(
            {
                "method": method,
                "profile": table["profile"].iat[0],
                "source": "run",
                "extract_seconds_per_image": per_image,
                "cached_seconds_per_pair": per_pair,
                "per_pair_seconds_per_pair": 2 * per_image + per_pair,
                "measured_on": f"run: {Path(output_dir).name} ({len(table)} pairs), "
                f"{run['environment']['device_name']}, finished {run['finished_at']}",
            }
        )
    return pd.DataFrame(rows)


def estimate_official_runtime(costs: pd.DataFrame, sizes: pd.DataFrame) -> pd.DataFrame:
    """Hours of each official sequence x costed (method, profile), both pipelines.

    Ours: unique images x seconds per image + pairs x our seconds per pair. The per-pair
    pipeline: pairs x its seconds per pair.
    """
    rows = []
    for _, cost in costs.iterrows():
        for _, size in sizes.iterrows():
            cached_seconds = (
                size["n_images"] * cost["extract_seconds_per_image"] + size["n_pairs"] * cost["cached_seconds_per_pair"]
            )
            reference_seconds = size["n_pairs"] * cost["per_pair_seconds_per_pair"]
            rows.append(
                {
                    "sequence": size["sequence"],
                    "method": cost["method"],
                    "profile": cost["profile"],
                    "source": cost["source"],
                    "n_pairs": size["n_pairs"],
                    "n_images": size["n_images"],
                    "cached_hours": cached_seconds / 3600,
                    "per_pair_hours": reference_seconds / 3600,
                    "speedup": reference_seconds / cached_seconds,
                    "measured_on": cost["measured_on"],
                }
            )
    return pd.DataFrame(rows)


def print_estimate(
    bench_dir: Path = DEFAULT_BENCH_DIR, gt_dir: Path | None = None, runs: Path | None = None
) -> pd.DataFrame:
    """Print (and write ``estimate.csv``) the official-sequence estimate from ``summary.csv``
    and, with ``runs`` (a sequence output folder), from every method that ran there."""
    from gvbench_nb.runner.config import data_dir

    summary_path = Path(bench_dir) / "summary.csv"
    if not summary_path.is_file() and runs is None:
        raise FileNotFoundError(
            f"no bench summary at {summary_path}: run `python -m gvbench_nb.speed PARAMS` "
            "first, or give --runs outputs/<sequence>"
        )
    if gt_dir is None:
        gt_dir = data_dir() / "gvbench_gt"
    sizes = official_sequence_sizes(gt_dir)
    costs = [costs_from_bench(pd.read_csv(summary_path, keep_default_na=False))] if summary_path.is_file() else []
    if runs is not None:
        costs.append(costs_from_runs(Path(runs)))
    estimate = estimate_official_runtime(pd.concat(costs, ignore_index=True), sizes)
    atomic_write_csv(Path(bench_dir) / "estimate.csv", estimate)
    print("Official sequences (from their pair lists):")
    print(sizes.to_string(index=False, float_format=lambda v: f"{v:.2f}"))
    totals = estimate.groupby(["source", "method", "profile"], sort=False)[["cached_hours", "per_pair_hours"]].sum()
    print("\nEstimated hours on this CPU (extraction cost per image and matching cost per pair as measured):")
    print(estimate.drop(columns="measured_on").to_string(index=False, float_format=lambda v: f"{v:.2f}"))
    print("\nAll six sequences, per method:")
    print(totals.to_string(float_format=lambda v: f"{v:.2f}"))
    print(
        "\nCaveats: measured on Gardens Point (960x540 images); the official images differ in size "
        "(extraction scales roughly with pixels, matching with keypoints), and the machine was shared "
        "(load averages in summary.csv). Treat these as order-of-magnitude figures."
    )
    print(GPU_NOTE)
    return estimate


def print_render_time(bench_dir: Path, n_frames: int, repeats: int, workers: int | None) -> pd.DataFrame:
    """Time the condition sweep's renderer and write ``render.csv`` (one row a setting)."""
    from gvbench_nb.studies.condition_sweep import time_render

    table = time_render(n_frames=n_frames, repeats=repeats, workers=workers)
    _merge_csv(Path(bench_dir) / "render.csv", table, ["setting", "n_frames", "image_size", "workers"])
    print(
        f"render time of one {n_frames}-frame query traversal ({table['image_size'].iat[0]}, "
        f"{table['workers'].iat[0]} worker threads, median of {repeats}; scene built once in "
        f"{table['scene_seconds'].iat[0]:.1f} s):"
    )
    print(
        table[["setting", "median_seconds", "min_seconds", "max_seconds", "loadavg_1m"]].to_string(
            index=False, float_format=lambda v: f"{v:.1f}"
        )
    )
    print(f"written to {Path(bench_dir) / 'render.csv'}\n")
    return table


# ------------------------------------------------------------------------- CLI --
def build_parser() -> argparse.ArgumentParser:
    """``python -m gvbench_nb.speed``: the bench, a program of its own beside the package's CLI."""
    bench = argparse.ArgumentParser(
        prog="python -m gvbench_nb.speed",
        description="Time our cached pipeline against the per-pair reference pipeline on the same pairs: "
        "both run on the same pairs (cold cache in a temporary folder each repeat), the bench fails if any "
        "pair's num_inliers differ, and writes per-repeat, summary and scaling CSVs. With --estimate alone "
        "(no params), prints the official-sequence estimate from the summary.",
    )
    bench.add_argument(
        "--debug", action="store_true", help="show the full traceback of an error instead of its one-line message"
    )
    bench.add_argument("params", nargs="?", help="params YAML, e.g. params/gardens_point.yaml")
    bench.add_argument("--methods", help="comma-separated method names (default: the params')")
    bench.add_argument("--limit", type=int, help="only the first N pairs, as in `run` (default: every pair)")
    bench.add_argument("--repeats", type=int, default=3, help="repeats per method; medians reported (default 3)")
    bench.add_argument("--profile", help="'paper' or 'repository' (default: the params')")
    bench.add_argument("--device", help="override the params' device")
    bench.add_argument(
        "--threads",
        type=int,
        help="torch and OpenCV threads for both pipelines (default: every core; on a loaded "
        "machine fewer threads than cores avoids spin-waiting, see the report)",
    )
    add_jobs_argument(
        bench,
        DEFAULT_BENCH_JOBS,
        f"images or pairs our pipeline runs at once, as `run --jobs` (default here {DEFAULT_BENCH_JOBS}; "
        "`run`'s is $GVBENCH_JOBS, else 1); the per-pair pipeline runs one pair at a time",
    )
    bench.add_argument("--bench-dir", default=str(DEFAULT_BENCH_DIR), help="where CSVs go (default outputs/bench)")
    bench.add_argument(
        "--scaling",
        default=",".join(map(str, DEFAULT_SCALING_LIMITS)),
        help="pair counts of the scaling table, or 'none' (default 50,100,200,400)",
    )
    bench.add_argument("--overlap", action="store_true", help="also measure whether prefetching hides decoding")
    bench.add_argument("--cprofile", action="store_true", help="also write a cProfile report of our pipeline")
    bench.add_argument("--estimate", action="store_true", help="print the official-sequence estimate at the end")
    bench.add_argument(
        "--runs",
        help="with --estimate: also cost every method that ran in this sequence output "
        "folder, from its per-pair timers (e.g. outputs/gardens_point)",
    )
    bench.add_argument(
        "--render",
        action="store_true",
        help="time rendering one synthetic query traversal, clear and under each condition at "
        "strength 1 (writes render.csv); needs no params",
    )
    bench.add_argument("--frames", type=int, default=100, help="frames of the --render traversal (default 100)")
    bench.set_defaults(handler=command_bench)
    return bench


def main(argv: list[str] | None = None) -> int:
    from gvbench_nb import cli

    return cli.main(argv, build_parser, "gvbench_nb.speed")


def command_bench(args: argparse.Namespace) -> int:
    import torch

    from gvbench_nb.protocol.features.base import resolve_device
    from gvbench_nb.runner import config

    bench_dir = Path(args.bench_dir)
    if args.estimate:  # before any timing: the estimate at the end would fail without them
        require_official_lists(config.data_dir() / "gvbench_gt")
    if args.render:
        print_render_time(bench_dir, args.frames, args.repeats, args.threads)
    if args.params is None:
        if not (args.estimate or args.render):
            raise config.ParamsError("bench needs a params file (or --estimate or --render alone)")
        if args.estimate:
            print_estimate(bench_dir, runs=args.runs)
        return 0
    if args.repeats < 1:
        raise config.ParamsError(f"--repeats must be at least 1, got {args.repeats}")
    params = config.load_params(args.params, methods=args.methods, profile=args.profile, device=args.device)
    full = config.prepare_sequence(params)  # the limit applies below (scaling needs the longer prefix)
    sequence = full.limited(args.limit)
    concurrency.configure_threads(args.threads)
    profile, device, seed = params["profile"], params["device"], params["seed"]
    print(
        f"{sequence.name}: {len(sequence.pairs)} pairs, {len(sequence.images)} unique images, profile {profile}, "
        f"torch threads {torch.get_num_threads()}, OpenCV threads {cv2.getNumThreads()}, "
        f"{os.cpu_count()} CPUs, load average {os.getloadavg()[0]:.2f}"
    )
    for method in params["methods"]:
        rows = bench_method(sequence, method, profile, args.repeats, device, seed, workers=args.jobs)
        _merge_csv(bench_dir / f"{sequence.name}_{method}.csv", rows, ["profile", "n_pairs"])
        summary = summarize_bench(rows)
        _merge_csv(bench_dir / "summary.csv", summary, ["sequence", "method", "profile", "n_pairs"])
        print_summary(summary)
        if args.scaling != "none":
            limits = tuple(int(v) for v in args.scaling.split(","))
            per_image = summary[f"{PER_PAIR}_extract_seconds_per_pair"].iat[0] / 2
            scaling = scaling_table(full, method, profile, limits, device, seed, per_image)
            _merge_csv(bench_dir / f"scaling_{sequence.name}_{method}.csv", scaling, ["profile", "n_pairs"])
            print(f"\nscaling ({method}, {profile}; stage sums of one cold run on {max(limits)} pairs):")
            print(
                scaling[
                    [
                        "n_pairs",
                        "n_images",
                        "uses_per_image",
                        "extract_seconds",
                        "match_seconds",
                        "verify_seconds",
                        "total_seconds",
                        "per_pair_total_seconds",
                        "speedup_from_stage_sums",
                    ]
                ].to_string(index=False, float_format=lambda v: f"{v:.3f}")
            )
        if args.overlap and not method_registry.is_dense(method_registry.resolve_method(method, profile)):
            overlap = pd.DataFrame([measure_prefetch_overlap(sequence, method, profile, device)])
            _merge_csv(bench_dir / "overlap.csv", overlap, ["sequence", "method", "profile", "n_images"])
            print(
                "\nprefetch overlap:\n" + overlap.iloc[:, :9].to_string(index=False, float_format=lambda v: f"{v:.3f}")
            )
        if args.cprofile:
            report = profile_pipeline(sequence, method, profile, device, seed)
            path = bench_dir / f"cprofile_{sequence.name}_{method}_{profile}.txt"
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_text(report)
            print(f"\ncProfile report: {path}")
    print(f"\nCSVs in {bench_dir}: {sequence.name}_<method>.csv, summary.csv, scaling_{sequence.name}_<method>.csv")
    if args.estimate:
        print()
        print_estimate(bench_dir, runs=args.runs)
    else:
        print(GPU_NOTE if resolve_device(device).type != "cuda" else "")
    return 0
