"""SUE: spatial uncertainty of a retrieval (Zaffar et al., CVPR 2024), training-free (MODELS.md
section 7): confidence = -(softmax(-slope * d)-weighted variance of the top-K positions, averaged
over the axes); frame indices (Q, K) serve as 1-D positions. Weights use d - min d (no underflow)."""

from __future__ import annotations

import numpy as np

SLOPE = 350.0  # the paper's value
TOP_K = 10


def sue_weights(distances: np.ndarray, slope: float = SLOPE) -> np.ndarray:
    """(Q, K) descriptor distances -> (Q, K) weights exp(-slope d), each row summing to 1."""
    d = np.asarray(distances, dtype=np.float64)
    if d.ndim == 1:
        d = d[None]
    logits = -slope * (d - d.min(axis=1, keepdims=True))  # shift: stable, same after normalising
    w = np.exp(logits)
    return w / w.sum(axis=1, keepdims=True)


def sue(distances: np.ndarray, positions: np.ndarray, slope: float = SLOPE, k: int | None = None) -> np.ndarray:
    """Spatial uncertainty (Q,), >= 0, of (Q, K) distances and (Q, K[, D]) positions; ``slope``
    350 in the paper; ``k`` uses only the first k columns (None: all)."""
    d = np.asarray(distances, dtype=np.float64)
    p = np.asarray(positions, dtype=np.float64)
    if d.ndim == 1:  # a single query
        d, p = d[None], p[None]
    if p.ndim == 2:  # 1-D positions (frame index)
        p = p[:, :, None]
    if p.shape[:2] != d.shape:
        raise ValueError(f"positions {p.shape} do not match distances {d.shape} on (Q, K)")
    if k is not None:
        d, p = d[:, :k], p[:, :k]
    w = sue_weights(d, slope)[:, :, None]  # (Q, K, 1)
    mu = (w * p).sum(axis=1, keepdims=True)  # (Q, 1, D)
    variance = (w * (p - mu) ** 2).sum(axis=1)  # (Q, D)
    return variance.mean(axis=1)


def sue_confidence(
    distances: np.ndarray, positions: np.ndarray, slope: float = SLOPE, k: int | None = None
) -> np.ndarray:
    """Confidence that each query's top-1 retrieval is right: -SUE (Q,), the score for AP / PR curves."""
    return -sue(distances, positions, slope, k)


__all__ = ["SLOPE", "TOP_K", "sue", "sue_confidence", "sue_weights"]
