"""Nearest-neighbour matching against a brute-force reference (hloc's rules, argmax ties)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from gvbench_nb.matchers import nearest_neighbour_matches


def brute_force_matches(distance: np.ndarray, mutual: bool, ratio: float | None, threshold: float | None
                        ) -> np.ndarray:
    """(M, 2) matches from a full distance matrix, one row at a time; ties go to the first index."""
    matches = []
    for i, row in enumerate(distance):
        j = int(np.argmin(row))
        if mutual and int(np.argmin(distance[:, j])) != i:
            continue
        if ratio is not None and len(row) > 1 and not row[j] ** 2 <= ratio**2 * np.sort(row)[1] ** 2:
            continue
        if threshold is not None and not row[j] ** 2 <= threshold**2:
            continue
        matches.append((i, j))
    return np.array(matches, dtype=np.int64).reshape(-1, 2)


RULES = [(True, 0.8, None), (True, None, None), (False, 0.8, None), (True, 0.9, 0.7), (False, None, None)]


@pytest.mark.parametrize("mutual, ratio, threshold", RULES)
def test_l2_matches_equal_brute_force_with_duplicated_descriptors(mutual, ratio, threshold):
    rng = np.random.default_rng(1)
    descriptors0 = rng.normal(size=(300, 32)).astype(np.float32)
    descriptors1 = np.concatenate([descriptors0[:120] + 0.3 * rng.normal(size=(120, 32)),
                                   rng.normal(size=(100, 32))]).astype(np.float32)
    descriptors0[50] = descriptors0[10]  # identical descriptors tie on every column
    descriptors1[7] = descriptors1[3]
    normalised0 = descriptors0 / np.linalg.norm(descriptors0, axis=1, keepdims=True)
    normalised1 = descriptors1 / np.linalg.norm(descriptors1, axis=1, keepdims=True)
    distance = np.sqrt(np.clip(2 - 2 * normalised0 @ normalised1.T, 0, None))
    expected = brute_force_matches(distance, mutual, ratio, threshold)

    matches, scores = nearest_neighbour_matches(torch.from_numpy(descriptors0), torch.from_numpy(descriptors1),
                                                mutual=mutual, ratio_threshold=ratio, distance_threshold=threshold)

    assert len(expected) > 20  # the case is not vacuous
    np.testing.assert_array_equal(matches.numpy(), expected)
    similarity = (normalised0 @ normalised1.T)[expected[:, 0], expected[:, 1]]
    np.testing.assert_allclose(scores.numpy(), (similarity + 1) / 2, atol=1e-5)
    if mutual:
        assert len(np.unique(matches[:, 1].numpy())) == len(matches)  # one-to-one despite the duplicates


@pytest.mark.parametrize("mutual, ratio, threshold", [(True, 0.8, None), (True, None, None), (True, None, 20.0),
                                                       (False, None, None)])
def test_hamming_matches_equal_brute_force_under_frequent_ties(mutual, ratio, threshold):
    rng = np.random.default_rng(2)
    # 64-bit descriptors: integer distances tie often, which is where tie rules show.
    binary0 = rng.integers(0, 256, (200, 8), dtype=np.uint8)
    bits0 = np.unpackbits(binary0, axis=1)
    noisy = bits0[:100] ^ (rng.random((100, 64)) < 0.08)  # near copies: the ratio test passes some
    bits1 = np.concatenate([noisy, rng.integers(0, 2, (50, 64))]).astype(np.uint8)
    binary1 = np.packbits(bits1, axis=1)
    distance = (bits0[:, None, :] != bits1[None, :, :]).sum(-1).astype(np.float64)
    expected = brute_force_matches(distance, mutual, ratio, threshold)

    matches, scores = nearest_neighbour_matches(torch.from_numpy(binary0), torch.from_numpy(binary1),
                                                mutual=mutual, ratio_threshold=ratio, distance_threshold=threshold,
                                                metric="hamming")

    assert len(expected) > 10
    np.testing.assert_array_equal(matches.numpy(), expected)
    np.testing.assert_allclose(scores.numpy(), 1 - distance[expected[:, 0], expected[:, 1]] / 64, atol=1e-6)


def test_empty_and_single_column_inputs():
    empty, _ = nearest_neighbour_matches(torch.zeros((0, 8)), torch.ones((5, 8)), ratio_threshold=0.8)
    assert empty.shape == (0, 2)
    # One reference descriptor: the ratio test has no second neighbour and is skipped.
    matches, _ = nearest_neighbour_matches(torch.eye(3), torch.eye(3)[:1], ratio_threshold=0.8)
    np.testing.assert_array_equal(matches.numpy(), [[0, 0]])


def test_unknown_metric_is_named():
    with pytest.raises(ValueError, match="unknown metric 'cosine'"):
        nearest_neighbour_matches(torch.ones((2, 4)), torch.ones((2, 4)), metric="cosine")
