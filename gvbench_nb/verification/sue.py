"""SUE: spatial uncertainty of a retrieval (Zaffar et al., CVPR 2024), training-free.

A query's top-1 retrieval is trusted when its top-K references lie close together
on the map. With descriptor distances d_i and positions p_i of the top-K
(MODELS.md section 7):

    w_i = exp(-slope * d_i) / sum_j exp(-slope * d_j)        (slope = 350)
    mu  = sum_i w_i p_i
    SUE = (sum_i w_i (x_i - mu_x)^2 + sum_i w_i (y_i - mu_y)^2) / 2
    confidence = -SUE

i.e. the weighted variance of the positions, averaged over the two axes.

1-D positions: for frame-aligned sequences (Nordland, GV-Bench's sequences without
poses) the reference's frame index is its position; pass ``positions`` as (Q, K)
and SUE is the weighted variance of the indices (the average over one axis), in
frames squared. In general, positions (Q, K, D) give the mean over the D axes of
the weighted variances.

The weights are computed as ``exp(-slope * (d_i - min_j d_j))`` before normalising:
the same numbers after normalisation, but no underflow to 0/0 when every distance
is large (exp(-350 * 3) is 0 in float64).
"""

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
    """Spatial uncertainty (Q,), >= 0: the weighted positional variance of the top-K.

    Args:
        distances: (Q, K) descriptor distances of each query's retrieved references.
        positions: (Q, K, 2) reference positions (x, y), or (Q, K) for 1-D positions
            such as frame indices, or (Q, K, D) in general.
        slope: sharpness of the weights (350 in the paper).
        k: use only the first ``k`` columns (the top-k, if given in retrieval order);
            ``None`` uses all K given.
    """
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
    """Confidence that each query's top-1 retrieval is right: -SUE, shape (Q,).

    Higher is more confident; use it as the score for AP / PR curves.
    """
    return -sue(distances, positions, slope, k)


__all__ = ["SLOPE", "TOP_K", "sue", "sue_confidence", "sue_weights"]
