"""Hamming matching by popcount against a brute-force reference written from hloc's rule.

hloc (``hloc/matchers/nearest_neighbor.py``) finds each row's two nearest columns and each
column's two nearest rows, applies the ratio and distance tests in both directions, then keeps
a row's match only when its column's surviving match points back. Ties go to the lower index.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from gvbench_nb.protocol.matching.nearest_neighbour import (
    NearestNeighbourMatcher,
    hamming_distances,
    hamming_nearest_neighbour_matches,
)


def bit_distances(binary0: np.ndarray, binary1: np.ndarray) -> np.ndarray:
    """Full Hamming distance matrix from unpacked bits, no popcount involved."""
    bits0, bits1 = np.unpackbits(binary0, axis=1), np.unpackbits(binary1, axis=1)
    return (bits0[:, None, :] != bits1[None, :, :]).sum(-1).astype(np.float64)


def one_direction(distance: np.ndarray, ratio: float | None, threshold: float | None) -> list[int]:
    """Each row's nearest column (first of equal distances) or -1 where a test rejects it."""
    result = []
    for row in distance:
        j = int(np.argmin(row))
        ordered = np.sort(row)
        ok = True
        if ratio is not None and not ordered[0] ** 2 <= ratio**2 * ordered[1] ** 2:
            ok = False
        if threshold is not None and not row[j] ** 2 <= threshold**2:
            ok = False
        result.append(j if ok else -1)
    return result


def reference_matches(distance: np.ndarray, mutual: bool, ratio: float | None, threshold: float | None) -> np.ndarray:
    if min(distance.shape) == 1:
        ratio = None  # no second neighbour on one side: hloc drops the ratio test
    forward = one_direction(distance, ratio, threshold)
    backward = one_direction(distance.T, ratio, threshold) if mutual else None
    pairs = [(i, j) for i, j in enumerate(forward) if j >= 0 and (backward is None or backward[j] == i)]
    return np.array(pairs, dtype=np.int64).reshape(-1, 2)


def row_only_matches(distance: np.ndarray, ratio: float) -> set[tuple[int, int]]:
    """The rule this replaced: ratio on rows only, then a plain column argmin for mutuality."""
    return {
        (i, j)
        for i, j in enumerate(one_direction(distance, ratio, None))
        if j >= 0 and int(np.argmin(distance[:, j])) == i
    }


def tie_heavy(rng: np.random.Generator, n0: int, n1: int, n_bytes: int) -> tuple[np.ndarray, np.ndarray]:
    """Sparse descriptors (few set bits) with duplicated rows: many equal distances everywhere."""
    bits0 = (rng.random((n0, 8 * n_bytes)) < 0.04).astype(np.uint8)
    bits1 = (rng.random((n1, 8 * n_bytes)) < 0.04).astype(np.uint8)
    bits1[:100] = bits0[:100] ^ (rng.random((100, 8 * n_bytes)) < 0.01)  # near copies pass the ratio test
    binary0, binary1 = np.packbits(bits0, axis=1), np.packbits(bits1, axis=1)
    binary0[5:15] = binary0[0]
    binary1[20:30] = binary1[3]
    binary1[40:45] = binary0[7]  # exact copies: distance 0 ties with distance 0
    return binary0, binary1


def near_copies(rng: np.random.Generator, n0: int, n1: int, n_bytes: int) -> tuple[np.ndarray, np.ndarray]:
    """Noisy copies plus random rows: matches that pass the ratio test, as on real images."""
    bits0 = rng.integers(0, 2, (n0, 8 * n_bytes), dtype=np.uint8)
    noisy = bits0[: n1 // 2] ^ (rng.random((n1 // 2, 8 * n_bytes)) < 0.1).astype(np.uint8)
    bits1 = np.concatenate([noisy, rng.integers(0, 2, (n1 - n1 // 2, 8 * n_bytes), dtype=np.uint8)])
    return np.packbits(bits0, axis=1), np.packbits(bits1, axis=1)


# threshold as a fraction of the descriptor's bits
RULES = [
    (True, 0.8, None),
    (True, None, None),
    (False, 0.8, None),
    (True, 0.9, 0.15),
    (False, None, None),
    (True, None, 0.11),
]


@pytest.mark.parametrize("mutual, ratio, threshold", RULES)
@pytest.mark.parametrize("make, n_bytes", [(tie_heavy, 8), (tie_heavy, 32), (near_copies, 32), (near_copies, 8)])
def test_matches_equal_brute_force(make, n_bytes, mutual, ratio, threshold):
    threshold = threshold and threshold * 8 * n_bytes
    rng = np.random.default_rng(n_bytes)
    binary0, binary1 = make(rng, 300, 260, n_bytes)
    distance = bit_distances(binary0, binary1)
    expected = reference_matches(distance, mutual, ratio, threshold)

    matches, scores = hamming_nearest_neighbour_matches(
        binary0, binary1, mutual=mutual, ratio_threshold=ratio, distance_threshold=threshold
    )

    assert len(expected) > 5  # the case is not vacuous
    np.testing.assert_array_equal(matches, expected)
    assert matches.dtype == np.int64 and scores.dtype == np.float32
    np.testing.assert_allclose(scores, 1 - distance[expected[:, 0], expected[:, 1]] / (8 * n_bytes), atol=1e-6)
    if mutual:
        assert len(np.unique(matches[:, 1])) == len(matches)  # one-to-one despite the duplicates


@pytest.mark.parametrize("n_bytes, rows_per_block", [(32, 512), (32, 7), (5, 3), (1, 100)])
def test_popcount_distances_equal_bit_comparison(n_bytes, rows_per_block):
    rng = np.random.default_rng(n_bytes)
    binary0 = rng.integers(0, 256, (41, n_bytes), dtype=np.uint8)
    binary1 = rng.integers(0, 256, (23, n_bytes), dtype=np.uint8)
    distance = hamming_distances(binary0, binary1, rows_per_block=rows_per_block)
    assert distance.dtype == np.uint16
    np.testing.assert_array_equal(distance, bit_distances(binary0, binary1))


def test_ties_go_to_the_lower_index():
    # Row 0 is equally far (1 bit) from columns 1 and 2 and exactly equal to none: without the
    # ratio test it must take column 1; column 1's nearest rows tie too and must give row 0.
    binary0 = np.array([[0b0000_0011], [0b1111_0000]], np.uint8)
    binary1 = np.array([[0b1111_1111], [0b0000_0001], [0b0000_0010]], np.uint8)
    matches, _ = hamming_nearest_neighbour_matches(binary0, binary1, mutual=False)
    np.testing.assert_array_equal(matches, [[0, 1], [1, 0]])
    matches, _ = hamming_nearest_neighbour_matches(binary0, binary1, mutual=True)
    np.testing.assert_array_equal(matches, [[0, 1], [1, 0]])
    # A tie at the nearest distance fails the ratio test (d1 == d2), unless both are 0 bits.
    matches, _ = hamming_nearest_neighbour_matches(binary0, binary1, mutual=False, ratio_threshold=0.8)
    np.testing.assert_array_equal(matches, [[1, 0]])


def test_ratio_is_tested_on_columns_too():
    """The case where hloc's rule and a row-only ratio test differ, so a regression shows."""
    rng = np.random.default_rng(7)
    binary0, binary1 = near_copies(rng, 400, 200, 8)
    binary0[300:340] = np.packbits(np.unpackbits(binary1[:40], axis=1) ^ (rng.random((40, 64)) < 0.05), axis=1)
    distance = bit_distances(binary0, binary1)
    expected = {tuple(m) for m in reference_matches(distance, True, 0.8, None)}
    assert row_only_matches(distance, 0.8) - expected  # some matches fail only on their column's ratio

    matches, _ = hamming_nearest_neighbour_matches(binary0, binary1, mutual=True, ratio_threshold=0.8)

    assert {tuple(m) for m in matches} == expected


def test_single_descriptor_and_empty_sides():
    rng = np.random.default_rng(3)
    binary0 = rng.integers(0, 256, (20, 32), dtype=np.uint8)
    one = binary0[4:5] ^ np.uint8(1)
    for mutual in (True, False):
        matches, scores = hamming_nearest_neighbour_matches(binary0, one, mutual=mutual, ratio_threshold=0.8)
        expected = reference_matches(bit_distances(binary0, one), mutual, 0.8, None)
        np.testing.assert_array_equal(matches, expected)
        matches, _ = hamming_nearest_neighbour_matches(one, binary0, mutual=mutual, ratio_threshold=0.8)
        np.testing.assert_array_equal(matches, reference_matches(bit_distances(one, binary0), mutual, 0.8, None))
    matches, scores = hamming_nearest_neighbour_matches(binary0[:0], binary0, ratio_threshold=0.8)
    assert matches.shape == (0, 2) and scores.shape == (0,)
    matches, _ = hamming_nearest_neighbour_matches(binary0, binary0[:0])
    assert matches.shape == (0, 2)


def test_the_nn_matcher_dispatches_hamming_here():
    rng = np.random.default_rng(4)
    binary0, binary1 = near_copies(rng, 120, 100, 32)
    conf = {"type": "nn", "metric": "hamming", "mutual": True, "ratio_threshold": 0.8}
    matches, scores = NearestNeighbourMatcher(conf, torch.device("cpu"))(
        {"descriptors": binary0}, {"descriptors": binary1}
    )
    expected = reference_matches(bit_distances(binary0, binary1), True, 0.8, None)
    assert len(expected) > 20
    np.testing.assert_array_equal(matches, expected)
