"""What one sift-nn or orb-nn pair's matching costs, against what it cannot avoid, on one thread.

Both our nearest-neighbour matcher and vismatch's (OpenCV's brute-force k=2 search) compute every
descriptor distance of a pair: a (2048 x 128) by (128 x 2048) product at the repository profile's
2048 keypoints for SIFT, 2048 x 2048 Hamming distances of 256 bits for ORB. This times, on one
thread and alternating, on random descriptors (seed 0): that product alone, our matcher under the
repository profile's rule (ratio 0.75, one way) and OpenCV's ``BFMatcher.knnMatch(k=2)``; for ORB,
the Hamming kernel under both orb-nn rules (the repository's one-way knn ratio 0.75, hloc's two-way
ratio 0.8 with the mutual check, the paper profile's) beside main's implementation at ada2794 (kept
below as it was: every distance by numpy's ``bitwise_count`` in row blocks, then each direction's
two nearest from the matrix) and OpenCV's Hamming k=2 search, and prints the medians.

``--pairs PARAMS`` instead runs orb-nn's matcher of both profiles on every pair of a params file
(ORB features extracted by the package into ``--cache-dir``) with the kernel and with main's
implementation, alternating, on one thread: it counts the pairs whose matches or scores differ
(ties included) and prints each side's median time a pair.

    .venv/bin/python benchmarks/nn_matching_bound.py [--keypoints 2048] [--repeats 15]
    .venv/bin/python benchmarks/nn_matching_bound.py --pairs params/gardens_point.yaml
"""

from __future__ import annotations

import argparse
import statistics
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import torch

from gvbench_nb.protocol.matching.nearest_neighbour import (
    NearestNeighbourMatcher,
    _passes,
    _two_nearest,
    hamming_nearest_neighbour_matches,
)

Matches = tuple[np.ndarray, np.ndarray]


# --------------------------------------------- main's Hamming matching (ada2794), one thread --
def main_hamming_distances(descriptors0: np.ndarray, descriptors1: np.ndarray, rows_per_block: int = 64) -> np.ndarray:
    """ada2794's ``hamming_distances`` on one thread: (N0, N1) uint16 popcounts of 64-bit XORs."""
    n_bytes = descriptors0.shape[1]
    padded = -n_bytes % 8

    def words(descriptors: np.ndarray) -> np.ndarray:
        descriptors = np.ascontiguousarray(descriptors, dtype=np.uint8)
        if padded:
            descriptors = np.pad(descriptors, ((0, 0), (0, padded)))
        return descriptors.view(np.uint64)

    words0, words1 = words(descriptors0), words(descriptors1)
    distance = np.empty((len(words0), len(words1)), np.uint16)
    columns = [np.ascontiguousarray(words1[:, word]) for word in range(words1.shape[1])]
    xor = np.empty((rows_per_block, len(words1)), np.uint64)
    count = np.empty((rows_per_block, len(words1)), np.uint8)
    for start in range(0, len(words0), rows_per_block):
        block = distance[start : start + rows_per_block]
        n = len(block)
        block[:] = 0
        for word, column in enumerate(columns):
            np.bitwise_xor(words0[start : start + n, word, None], column[None, :], out=xor[:n])
            np.bitwise_count(xor[:n], out=count[:n])
            block += count[:n]
    return distance


def main_orb_matches(descriptors0: np.ndarray, descriptors1: np.ndarray, conf: dict[str, Any]) -> Matches:
    """ada2794's orb-nn matching under a recipe's matcher conf: the repository's knn ratio (one way,
    strict) or hloc's rule (ratio on rows and columns, mutual check), from the whole distance matrix."""
    n_bits = 8 * descriptors0.shape[1]
    ratio = conf.get("ratio_threshold")
    if conf.get("rule", "hloc") == "knn_ratio":
        if len(descriptors0) == 0 or len(descriptors1) < 2:
            return np.zeros((0, 2), np.int64), np.zeros(0, np.float32)
        nearest, first, second = _two_nearest(main_hamming_distances(descriptors0, descriptors1))
        rows = np.flatnonzero(first < ratio * second)
        matches = np.stack([rows, nearest[rows]], axis=1).astype(np.int64)
        return matches, (1 - first[rows] / n_bits).astype(np.float32)
    if len(descriptors0) == 0 or len(descriptors1) == 0:
        return np.zeros((0, 2), np.int64), np.zeros(0, np.float32)
    if min(len(descriptors0), len(descriptors1)) == 1:
        ratio = None
    distance = main_hamming_distances(descriptors0, descriptors1)
    nearest1, first, second = _two_nearest(distance)
    keep = _passes(first, second, ratio, conf.get("distance_threshold"))
    if conf.get("mutual", True):
        nearest0, first_back, second_back = _two_nearest(cv2.transpose(distance))
        back = np.where(_passes(first_back, second_back, ratio, conf.get("distance_threshold")), nearest0, -1)
        keep &= back[nearest1] == np.arange(len(descriptors0))
    index0 = np.flatnonzero(keep)
    matches = np.stack([index0, nearest1[index0]], axis=1).astype(np.int64)
    return matches, (1 - first[index0] / n_bits).astype(np.float32)


# ------------------------------------------------------------------------ random descriptors --
def time_random(keypoints: int, repeats: int) -> None:
    rng = np.random.default_rng(0)
    descriptors0 = rng.random((keypoints, 128), dtype=np.float32)
    descriptors1 = rng.random((keypoints, 128), dtype=np.float32)
    tensor0, tensor1 = torch.from_numpy(descriptors0), torch.from_numpy(descriptors1)
    ours = NearestNeighbourMatcher({"mutual": False, "ratio_threshold": 0.75}, torch.device("cpu"))
    brute_force = cv2.BFMatcher(cv2.NORM_L2)
    features0, features1 = {"descriptors": descriptors0}, {"descriptors": descriptors1}
    binary0 = rng.integers(0, 256, (keypoints, 32), dtype=np.uint8)  # ORB: 256 bits
    binary1 = rng.integers(0, 256, (keypoints, 32), dtype=np.uint8)
    hamming = cv2.BFMatcher(cv2.NORM_HAMMING)
    one_way = {"mutual": False, "ratio_threshold": 0.75, "rule": "knn_ratio"}
    two_way = {"mutual": True, "ratio_threshold": 0.8}
    calls: dict[str, Callable[[], object]] = {
        "descriptor product": lambda: tensor0 @ tensor1.T,
        "ours (ratio 0.75, one way)": lambda: ours(features0, features1),
        "OpenCV BFMatcher knn k=2 (vismatch's)": lambda: brute_force.knnMatch(descriptors0, descriptors1, k=2),
        "ORB: main at ada2794, bitwise_count (ratio 0.75, one way)": lambda: main_orb_matches(
            binary0, binary1, one_way
        ),
        "ORB: ours, Hamming kernel (ratio 0.75, one way)": lambda: hamming_nearest_neighbour_matches(
            binary0, binary1, mutual=False, ratio_threshold=0.75
        ),
        "ORB: main at ada2794, bitwise_count (ratio 0.8, hloc's two-way rule)": lambda: main_orb_matches(
            binary0, binary1, two_way
        ),
        "ORB: ours, Hamming kernel (ratio 0.8, hloc's two-way rule)": lambda: hamming_nearest_neighbour_matches(
            binary0, binary1, mutual=True, ratio_threshold=0.8
        ),
        "ORB: OpenCV BFMatcher Hamming knn k=2 (vismatch's)": lambda: hamming.knnMatch(binary0, binary1, k=2),
    }
    timings = alternate(calls, repeats)
    print(f"{keypoints} x {keypoints} descriptors (128 floats; ORB: 32 bytes), one thread, medians of {repeats}:")
    for name, times in timings.items():
        print(f"  {name}: {statistics.median(times) * 1e3:.1f} ms")


def alternate(calls: dict[str, Callable[[], object]], repeats: int) -> dict[str, list[float]]:
    """Each call's times, the calls taken in turn ``repeats`` times after one warm-up each."""
    for call in calls.values():
        call()
    timings: dict[str, list[float]] = {name: [] for name in calls}
    for _ in range(repeats):
        for name, call in calls.items():
            start = time.perf_counter()
            call()
            timings[name].append(time.perf_counter() - start)
    return timings


# ------------------------------------------------------------------- every pair of a sequence --
def compare_pairs(params_path: str, cache_dir: Path) -> None:
    from parity_effects import read_features

    from gvbench_nb import methods
    from gvbench_nb.runner import config, image_features, sequence_build

    for profile in ("paper", "repository"):
        params = config.load_params(params_path, profile=profile)
        sequence = sequence_build.prepare_sequence(params)
        conf = methods.resolve_method("orb-nn", profile)
        image_features.extract_features(sequence, conf["extractor"], cache_dir, device="cpu", progress=False, jobs=1)
        features = read_features(sequence, conf["extractor"], cache_dir)
        kernel = NearestNeighbourMatcher(conf["matcher"], torch.device("cpu"))
        differing, n_matches, old_times, new_times = 0, 0, [], []
        for pair in sequence.pairs:
            descriptors0 = features(pair.query)["descriptors"]
            descriptors1 = features(pair.reference)["descriptors"]
            start = time.perf_counter()
            old = main_orb_matches(descriptors0, descriptors1, conf["matcher"])
            old_times.append(time.perf_counter() - start)
            start = time.perf_counter()
            new = kernel({"descriptors": descriptors0}, {"descriptors": descriptors1})
            new_times.append(time.perf_counter() - start)
            differing += not (np.array_equal(old[0], new[0]) and np.array_equal(old[1], new[1]))
            n_matches += len(new[0])
        print(
            f"orb-nn, {profile} profile, {len(sequence.pairs)} pairs of {params['sequence']} ({n_matches} matches): "
            f"{differing} pairs differ; a pair, one thread, median: main at ada2794 "
            f"{statistics.median(old_times) * 1e3:.1f} ms, kernel {statistics.median(new_times) * 1e3:.1f} ms"
        )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--keypoints", type=int, default=2048, help="descriptors an image (default 2048)")
    parser.add_argument("--repeats", type=int, default=15, help="alternating repeats (default 15)")
    parser.add_argument("--pairs", metavar="PARAMS", help="compare main's and the kernel's orb-nn on every pair")
    parser.add_argument("--cache-dir", default="outputs/nn_matching_bound/cache", help="--pairs' feature cache")
    args = parser.parse_args()
    torch.set_num_threads(1)
    cv2.setNumThreads(1)
    if args.pairs:
        compare_pairs(args.pairs, Path(args.cache_dir))
    else:
        time_random(args.keypoints, args.repeats)


if __name__ == "__main__":
    main()
