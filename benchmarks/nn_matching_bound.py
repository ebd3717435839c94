"""What one sift-nn pair's matching costs, against the descriptor product it cannot avoid.

Both our nearest-neighbour matcher and vismatch's (OpenCV's brute-force k=2 search) compute every
descriptor distance of a pair: a (2048 x 128) by (128 x 2048) product at the repository profile's
2048 keypoints. This times, on one thread and alternating, that product alone, our matcher under
the repository profile's rule (ratio 0.75, one way) and OpenCV's ``BFMatcher.knnMatch(k=2)``, on
random descriptors (seed 0), and the same for ORB's binary descriptors, and prints the medians: the product bounds how fast any exact
matcher can be, and so how far ahead of the peer's per-pair loop a run can get.

    .venv/bin/python benchmarks/nn_matching_bound.py [--keypoints 2048] [--repeats 15]
"""

from __future__ import annotations

import argparse
import statistics
import time

import cv2
import numpy as np
import torch

from gvbench_nb.protocol.matching.nearest_neighbour import NearestNeighbourMatcher, hamming_nearest_neighbour_matches


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--keypoints", type=int, default=2048, help="descriptors an image (default 2048)")
    parser.add_argument("--repeats", type=int, default=15, help="alternating repeats (default 15)")
    args = parser.parse_args()
    torch.set_num_threads(1)
    cv2.setNumThreads(1)
    rng = np.random.default_rng(0)
    descriptors0 = rng.random((args.keypoints, 128), dtype=np.float32)
    descriptors1 = rng.random((args.keypoints, 128), dtype=np.float32)
    tensor0, tensor1 = torch.from_numpy(descriptors0), torch.from_numpy(descriptors1)
    ours = NearestNeighbourMatcher({"mutual": False, "ratio_threshold": 0.75}, torch.device("cpu"))
    brute_force = cv2.BFMatcher(cv2.NORM_L2)
    features0, features1 = {"descriptors": descriptors0}, {"descriptors": descriptors1}
    binary0 = rng.integers(0, 256, (args.keypoints, 32), dtype=np.uint8)  # ORB: 256 bits
    binary1 = rng.integers(0, 256, (args.keypoints, 32), dtype=np.uint8)
    hamming = cv2.BFMatcher(cv2.NORM_HAMMING)
    timings: dict[str, list[float]] = {
        "descriptor product": [],
        "ours (ratio 0.75, one way)": [],
        "OpenCV BFMatcher knn k=2 (vismatch's)": [],
        "ORB: ours, popcount (ratio 0.75, one way)": [],
        "ORB: ours, popcount (ratio 0.8, hloc's two-way rule)": [],
        "ORB: OpenCV BFMatcher Hamming knn k=2 (vismatch's)": [],
    }
    calls = [
        lambda: tensor0 @ tensor1.T,
        lambda: ours(features0, features1),
        lambda: brute_force.knnMatch(descriptors0, descriptors1, k=2),
        lambda: hamming_nearest_neighbour_matches(binary0, binary1, mutual=False, ratio_threshold=0.75),
        lambda: hamming_nearest_neighbour_matches(binary0, binary1, mutual=True, ratio_threshold=0.8),
        lambda: hamming.knnMatch(binary0, binary1, k=2),
    ]
    for call in calls:
        call()  # warm-up
    for _ in range(args.repeats):
        for times, call in zip(timings.values(), calls):
            start = time.perf_counter()
            call()
            times.append(time.perf_counter() - start)
    print(
        f"{args.keypoints} x {args.keypoints} descriptors (128 floats; ORB: 32 bytes), one thread, "
        f"medians of {args.repeats}:"
    )
    for name, times in timings.items():
        print(f"  {name}: {statistics.median(times) * 1e3:.1f} ms")


if __name__ == "__main__":
    main()
