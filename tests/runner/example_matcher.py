"""An example matcher written outside the package: this one file, plus one method entry
(``methods.register_method`` or an entry a profile in ``protocol/recipes/``), is all a sparse matcher
needs. ``tests/runner/test_extending.py`` registers it and runs it end to end; docs/extending.md
walks through it.

A matcher class is built as ``Class(conf, device)`` and called on two feature dicts
(``keypoints`` (N, 2), ``descriptors`` (N, D), ``image_size``); it returns matches (M, 2)
int64 indices and scores (M,) float32.
"""

from __future__ import annotations

from typing import Any

import numpy as np


class MutualNearestNeighbourMatcher:
    """Mutual nearest neighbours of float descriptors by cosine similarity, in numpy."""

    def __init__(self, conf: dict[str, Any], device: Any) -> None:
        self.min_similarity = float(conf.get("min_similarity", -1.0))

    def __call__(
        self, features0: dict[str, np.ndarray], features1: dict[str, np.ndarray]
    ) -> tuple[np.ndarray, np.ndarray]:
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
