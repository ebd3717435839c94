"""SUE: spatial uncertainty of a retrieval (Zaffar et al., CVPR 2024), training-free (MODELS.md
section 7): confidence = -(softmax(-slope * d)-weighted variance of the top-K positions, averaged
over the axes); frame indices (Q, K) serve as 1-D positions."""

from __future__ import annotations

import numpy as np
from scipy.special import softmax

SLOPE = 350.0  # the paper's value


def sue_weights(distances: np.ndarray, slope: float = SLOPE) -> np.ndarray:
    """(Q, K) descriptor distances -> (Q, K) weights exp(-slope d), each row summing to 1."""
    return softmax(-slope * np.asarray(distances, dtype=np.float64), axis=1)  # shifted by the row's max: no underflow


def sue(distances: np.ndarray, positions: np.ndarray, slope: float = SLOPE) -> np.ndarray:
    """Spatial uncertainty (Q,), >= 0, of (Q, K) distances and (Q, K[, D]) positions (``slope`` 350
    in the paper); its negative is the confidence that a query's top-1 retrieval is right."""
    d = np.asarray(distances, dtype=np.float64)
    p = np.asarray(positions, dtype=np.float64)
    if p.ndim == 2:  # 1-D positions (frame index)
        p = p[:, :, None]
    if p.shape[:2] != d.shape:
        raise ValueError(f"positions {p.shape} do not match distances {d.shape} on (Q, K)")
    w = sue_weights(d, slope)[:, :, None]  # (Q, K, 1)
    mu = (w * p).sum(axis=1, keepdims=True)  # (Q, 1, D)
    variance = (w * (p - mu) ** 2).sum(axis=1)  # (Q, D)
    return variance.mean(axis=1)
