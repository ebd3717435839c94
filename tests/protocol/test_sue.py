"""SUE: spatial uncertainty of retrieval on hand-made positions."""

from __future__ import annotations

import numpy as np
import pytest

from gvbench_nb.verification.sue import SLOPE, sue, sue_weights


def test_clustered_more_confident_than_scattered():
    rng = np.random.default_rng(0)
    distances = np.tile(np.linspace(0.9, 1.0, 10), (2, 1))
    clustered = rng.normal([100.0, 50.0], 1.0, (10, 2))
    scattered = rng.uniform(0, 500, (10, 2))
    conf = -sue(distances, np.stack([clustered, scattered]))
    assert conf.shape == (2,)
    assert conf[0] > conf[1]
    assert np.all(conf <= 0)


def test_weights_normalised_and_follow_formula():
    rng = np.random.default_rng(2)
    distances = rng.uniform(0.5, 1.5, (4, 10))
    w = sue_weights(distances)
    np.testing.assert_allclose(w.sum(axis=1), 1.0)
    raw = np.exp(-SLOPE * distances)
    np.testing.assert_allclose(w, raw / raw.sum(axis=1, keepdims=True), rtol=1e-9)
    assert np.all(np.diff(w[:, np.argsort(distances[0])][0]) <= 0)  # closer -> heavier
    # large distances: exp(-350 d) underflows, the shifted form does not
    w_far = sue_weights(np.array([[5.0, 5.0, 6.0]]))
    np.testing.assert_allclose(w_far, [[0.5, 0.5, 0.0]], atol=1e-12)


def test_weighted_mean_and_spread_by_hand():
    # two references: weights (a, 1 - a) -> variance a (1 - a) (x1 - x0)^2 on one axis
    d = np.array([[0.0, 0.002]])
    a = 1 / (1 + np.exp(-SLOPE * 0.002))
    positions = np.array([[[0.0, 0.0], [10.0, 0.0]]])
    assert sue(d, positions)[0] == pytest.approx(a * (1 - a) * 100 / 2)


def test_equal_distances_give_plain_variance_of_2d_and_1d_positions():
    rng = np.random.default_rng(1)
    positions = rng.uniform(-10, 10, (5, 10, 2))
    distances = np.full((5, 10), 0.7)
    expected = positions.var(axis=1).mean(axis=1)  # (var_x + var_y) / 2, population variance
    np.testing.assert_allclose(sue(distances, positions), expected, rtol=1e-12)
    distances = np.full((2, 5), 1.0)
    frames = np.array([[100, 101, 102, 103, 104], [100, 400, 20, 900, 5]], dtype=float)
    s = sue(distances, frames)
    np.testing.assert_allclose(s, frames.var(axis=1))
    # 1-D equals 2-D with a constant second axis times 2 (mean over one axis, not two)
    flat = np.stack([frames, np.zeros_like(frames)], axis=-1)
    np.testing.assert_allclose(sue(distances, flat) * 2, s)
    with pytest.raises(ValueError, match="do not match"):
        sue(np.zeros((2, 3)), np.zeros((2, 4, 2)))
