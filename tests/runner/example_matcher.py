"""An example matcher written outside the package: this one file plus one method entry is all a
sparse matcher needs (docs/extending.md; tests/runner/test_extending.py runs it end to end)."""

from __future__ import annotations

from typing import Any

import numpy as np

from gvbench_nb.protocol.matching.base import Matcher, Matches


class MutualNearestNeighbourMatcher(Matcher):
    """Mutual nearest neighbours of float descriptors by cosine similarity, in numpy."""

    type = "example_mutual_nn"  # the recipe's type once this file is in protocol/matching/

    def __init__(self, conf: dict[str, Any], device: Any) -> None:
        super().__init__(conf, device)
        self.min_similarity = float(conf.get("min_similarity", -1.0))

    def __call__(self, features0: dict[str, np.ndarray], features1: dict[str, np.ndarray]) -> Matches:
        descriptors0 = features0["descriptors"].astype(np.float32)
        descriptors1 = features1["descriptors"].astype(np.float32)
        if len(descriptors0) == 0 or len(descriptors1) == 0:
            return np.zeros((0, 2), np.int64), np.zeros(0, np.float32)
        descriptors0 /= np.linalg.norm(descriptors0, axis=1, keepdims=True) + 1e-12
        descriptors1 /= np.linalg.norm(descriptors1, axis=1, keepdims=True) + 1e-12
        similarity = descriptors0 @ descriptors1.T
        best1 = similarity.argmax(axis=1)  # first maximum on ties, as torch's max
        best0 = similarity.argmax(axis=0)
        rows = np.flatnonzero(best0[best1] == np.arange(len(descriptors0)))
        best = similarity[rows, best1[rows]]
        keep = best >= self.min_similarity
        matches = np.stack([rows[keep], best1[rows][keep]], axis=1).astype(np.int64)
        return matches, ((best[keep] + 1) / 2).astype(np.float32)
