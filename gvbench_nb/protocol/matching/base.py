"""What every matcher shares.

A sparse matcher takes two feature dicts (from the cache: keypoints in original
pixels, descriptors, ``image_size`` as (width, height)) and returns ``matches`` (M, 2)
int64 indices into keypoints0/1 and ``scores`` (M,) float32. A dense matcher (class
attribute ``dense = True``) takes two prepared images and returns points and scores.
"""

from __future__ import annotations

from typing import Any, Protocol

import numpy as np

Matches = tuple[np.ndarray, np.ndarray]


class PreparedMatcher(Protocol):
    """A sparse matcher that, when ``can_prepare``, does its per-image work once per image:
    ``prepare`` makes one image's state and ``match_prepared`` matches two such states."""

    can_prepare: bool

    def prepare(self, features: dict[str, np.ndarray]) -> Any: ...

    def match_prepared(self, prepared0: Any, prepared1: Any) -> Matches: ...


def empty_matches() -> Matches:
    return np.zeros((0, 2), np.int64), np.zeros((0,), np.float32)
