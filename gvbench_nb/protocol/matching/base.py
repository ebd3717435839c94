"""What every matcher shares: its contract and the empty result."""

from __future__ import annotations

from typing import Any, ClassVar, Protocol

import numpy as np

from gvbench_nb.protocol.registry import Model

Matches = tuple[np.ndarray, np.ndarray]


class Matcher(Model):
    """A sparse matcher is called on two feature dicts (keypoints in original pixels,
    descriptors, ``image_size`` (width, height)) and returns ``matches`` (M, 2) int64 and
    ``scores`` (M,) float32; a dense one (``dense = True``, no extractor in its recipe) on two
    prepared images, returning points in each and confidences."""

    types: ClassVar[dict[str, type[Model]]] = {}
    dense: ClassVar[bool] = False

    def __call__(self, *inputs: Any) -> Any:
        raise NotImplementedError


class PreparedMatcher(Protocol):
    """A sparse matcher that, when ``can_prepare``, does its per-image work once per image:
    ``prepare`` makes one image's state and ``match_prepared`` matches two such states."""

    can_prepare: bool

    def prepare(self, features: dict[str, np.ndarray]) -> Any: ...

    def match_prepared(self, prepared0: Any, prepared1: Any) -> Matches: ...


def empty_matches() -> Matches:
    return np.zeros((0, 2), np.int64), np.zeros((0,), np.float32)
