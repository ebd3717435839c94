"""What every matcher shares.

A sparse matcher takes two feature dicts (from the cache: keypoints in original
pixels, descriptors, ``image_size`` as (width, height)) and returns ``matches`` (M, 2)
int64 indices into keypoints0/1 and ``scores`` (M,) float32. A dense matcher (class
attribute ``dense = True``) takes two prepared images and returns points and scores.
"""

from __future__ import annotations

import numpy as np

Matches = tuple[np.ndarray, np.ndarray]



def empty_matches() -> Matches:
    return np.zeros((0, 2), np.int64), np.zeros((0,), np.float32)
