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

``python benchmarks/speed.py --estimate`` turns the summary into an estimate of the six
official sequences from their pair lists. Every number comes from a measurement
written by this module; none is typed in.
"""

from __future__ import annotations

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
from gvbench_nb.data.sequences import Sequence
from gvbench_nb.io_utils import atomic_write_csv
from gvbench_nb.protocol.images import load_for_extraction, to_original_pixels
from gvbench_nb.protocol.ransac import verify_matches
from gvbench_nb.runner import concurrency, image_features, method_runs, pair_matching

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
    time (``concurrency.job_count``): per-pair table and stage seconds (totals).

    ``extract`` is the wall time of extraction (decoding overlapped by the prefetcher);
    ``match``/``verify`` are the per-pair timers' sums, which overlap (matching runs a pair
    ahead of verification), so ``match_verify_wall`` is their stage's wall time; ``other``
    is the rest (writing stores, building the table).
    """
    cache_dir = Path(work_dir) / "cache"
    start = time.perf_counter()
    if not method_registry.is_dense(conf):
        image_features.extract_features(sequence, conf["extractor"], cache_dir, device, progress=False, jobs=workers)
    extracted = time.perf_counter()
    pair_matching.match_and_verify(sequence, conf, cache_dir, device, seed, progress=False, jobs=workers)
    matched = time.perf_counter()
    table = method_runs.pairs_table(sequence, conf, cache_dir, seed)
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
            sizes = (features0.get("image_size"), features1.get("image_size"))
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


def merge_csv(path: Path, new: pd.DataFrame, keys: list[str]) -> pd.DataFrame:
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
        full = method_runs.pairs_table(largest, conf, Path(work_dir) / "cache", seed)
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
        image_features.extract_features(sequence, extractor_conf, Path(work_dir), resolved, progress=False, jobs=1)
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


def print_render_time(bench_dir: Path, n_frames: int, repeats: int, workers: int | None) -> pd.DataFrame:
    """Time the condition sweep's renderer and write ``render.csv`` (one row a setting)."""
    from render_time import time_render

    table = time_render(n_frames=n_frames, repeats=repeats, workers=workers)
    merge_csv(Path(bench_dir) / "render.csv", table, ["setting", "n_frames", "image_size", "workers"])
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
