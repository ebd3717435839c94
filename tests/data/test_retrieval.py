"""Label rules, retrieval, recall, VLAD/BoW encodings on hand-made data."""

from __future__ import annotations

import numpy as np
import pytest

from gvbench_nb.data import retrieval as rt
from gvbench_nb.data.build_inputs import BuildError, parse_options


def labels(rule: str, params: dict | None, query: dict, reference: dict, pairs: list) -> np.ndarray:
    return rt.ground_truth_matrix(rule, params, query, reference)[tuple(np.array(pairs).T)]


def test_heading_difference_wraps_at_360() -> None:
    np.testing.assert_allclose(
        rt.heading_difference_deg([359.0, 10.0, 0.0, 90.0], [1.0, 350.0, 180.0, -270.0]), [2.0, 20.0, 180.0, 0.0]
    )


def test_pose_rule_distance_and_wrapped_heading() -> None:
    query = rt.frame_table(["q0", "q1"], positions=[[0.0, 0.0], [100.0, 0.0]], headings=[359.0, 90.0])
    positions = [[10.0, 0.0], [20.0, 15.0], [0.0, 5.0], [0.0, 5.0], [110.0, 0.0]]
    reference = rt.frame_table(
        [f"r{i}" for i in range(5)], positions=positions, headings=[1.0, 0.0, 45.0, 300.0, 180.0]
    )
    pairs = [(0, 0), (0, 1), (0, 2), (0, 3), (1, 4), (0, 4)]
    # r0: 10 m, 2 deg across 0 | r1: 25 m exactly (inclusive), 1 deg | r2: 46 deg |
    # r3: 59 deg | r4 vs q1: 10 m but 90 deg | r4 vs q0: 110 m
    np.testing.assert_array_equal(labels("pose", None, query, reference, pairs), [1, 1, 0, 0, 0, 0])
    loose = labels("pose", {"max_heading_deg": 60.0}, query, reference, pairs)
    np.testing.assert_array_equal(loose, [1, 1, 1, 1, 0, 0])
    no_heading = labels("pose", {"max_heading_deg": None, "max_distance_m": 10.0}, query, reference, pairs)
    np.testing.assert_array_equal(no_heading, [1, 0, 1, 1, 1, 0])


def test_frame_tolerance_and_manual_rules() -> None:
    truth = rt.ground_truth_matrix(
        "frame_tolerance", None, rt.frame_table(["q"] * 4, range(4)), rt.frame_table(["r"] * 6, range(6))
    )
    np.testing.assert_array_equal(truth, np.abs(np.arange(4)[:, None] - np.arange(6)[None, :]) <= 2)  # default k 2
    query, reference = rt.frame_table(["a", "b"]), rt.frame_table(["x", "y", "z"])
    params = {"true_pairs": [("a", "y"), ("b", "x"), ("b", "z"), ("c", "x")]}  # 'c' is not a query here
    truth = rt.ground_truth_matrix("manual", params, query, reference)
    np.testing.assert_array_equal(truth, [[False, True, False], [True, False, True]])


@pytest.mark.parametrize(
    "rule, params, message",
    [
        ("gps", None, "unknown label rule"),
        ("frame_tolerance", {"tolerance": 3}, "no parameter"),
        ("pose", None, "position"),
    ],
)
def test_rule_errors_are_clear(rule: str, params: dict | None, message: str) -> None:
    table = rt.frame_table(["a"])
    with pytest.raises(KeyError, match=message):
        rt.ground_truth_matrix(rule, params, table, table)


def test_retrieve_top_n_known_answer() -> None:
    reference = np.eye(4, dtype=np.float32)
    query = np.array([[0.1, 0.9, 0.3, 0.0], [0.0, 0.0, 0.0, 1.0], [0.5, 0.5, 0.0, 0.0]], np.float32)
    indices, similarities = rt.retrieve_top_n(query, reference, 2)
    np.testing.assert_array_equal(indices, [[1, 2], [3, 0], [0, 1]])  # tie 0/1 -> lower index first
    np.testing.assert_allclose(similarities, [[0.9, 0.3], [1.0, 0.0], [0.5, 0.5]])
    indices, _ = rt.retrieve_top_n(query, reference, 10)  # n capped at R
    assert indices.shape == (3, 4)


def test_recall_at_known_ranking() -> None:
    truth = np.zeros((4, 5), dtype=bool)
    truth[0, 2] = True  # found at rank 1
    truth[1, 4] = True  # found at rank 3
    truth[2, 0] = True  # never retrieved
    # query 3 has no true reference: excluded
    ranked = np.array([[2, 0, 1], [0, 1, 4], [1, 2, 3], [0, 1, 2]])
    recall = rt.retrieval_recall_at([1, 2, 3], ranked, truth)
    assert recall == pytest.approx(
        {"recall@1": 1 / 3, "recall@2": 1 / 3, "recall@3": 2 / 3, "queries_evaluated": 3, "queries_excluded": 1}
    )
    with pytest.raises(ValueError):
        rt.retrieval_recall_at([5], ranked, truth)


def test_choose_queries() -> None:
    np.testing.assert_array_equal(rt.choose_queries(5), np.arange(5))
    subset = rt.choose_queries(100, 10, seed=3)
    assert len(subset) == 10 and len(set(subset)) == 10 and np.all(np.diff(subset) > 0)
    np.testing.assert_array_equal(subset, rt.choose_queries(100, 10, seed=3))
    assert not np.array_equal(subset, rt.choose_queries(100, 10, seed=4))


def synthetic_local(seed: int, num_images: int = 12, dim: int = 16, binary: bool = False) -> dict[str, np.ndarray]:
    """Images whose descriptors come from image-specific mixtures of 8 modes."""
    rng = np.random.default_rng(seed)
    modes = rng.standard_normal((8, dim)) * 3
    local = {}
    for i in range(num_images):
        picks = rng.choice(8, size=60, p=np.roll([0.5, 0.2, 0.1, 0.05, 0.05, 0.05, 0.03, 0.02], i))
        data = modes[picks] + rng.standard_normal((60, dim)) * 0.3
        local[f"img{i:02d}"] = np.packbits(data > 0, axis=1) if binary else data.astype(np.float32)
    return local


@pytest.mark.parametrize("method, num_words, binary", [("vlad", 8, False), ("bow", 16, False), ("bow", 12, True)])
def test_encodings_deterministic_and_normalised(method: str, num_words: int, binary: bool) -> None:
    reference = synthetic_local(0, binary=binary)
    query = {k: v[::2] for k, v in synthetic_local(1, binary=binary).items()} | {"empty": reference["img00"][:0]}
    a = rt.GLOBAL_DESCRIPTORS[method](reference, query, num_words=num_words, seed=7)
    b = rt.GLOBAL_DESCRIPTORS[method](dict(reversed(reference.items())), query, num_words=num_words, seed=7)
    np.testing.assert_array_equal(a[1], b[1])  # same seed: identical, whatever the dict order
    norms = np.linalg.norm(np.vstack(a), axis=1)
    np.testing.assert_allclose(norms[:-1], 1.0, rtol=1e-5)
    assert norms[-1] == 0  # no descriptors -> zeros
    indices, _ = rt.retrieve_top_n(a[0], a[0], 1)  # each reference image retrieves itself first
    np.testing.assert_array_equal(indices[:, 0], np.arange(len(reference)))


def test_vlad_intra_normalised_blocks_and_binary_words() -> None:
    reference = synthetic_local(0)
    vector = rt.vlad_encode(reference["img03"], rt.fit_vocabulary(reference, 8)).reshape(8, 16)
    norms = np.linalg.norm(vector, axis=1)
    used = norms > 0
    np.testing.assert_allclose(norms[used], 1 / np.sqrt(used.sum()), rtol=1e-5)  # equal blocks before L2
    binary = synthetic_local(2, binary=True)
    assert rt.fit_vocabulary(binary, 12).shape == (12, binary["img00"].shape[1] * 8)  # unpacked bits


def test_unknown_global_descriptor() -> None:
    with pytest.raises(BuildError, match="Known: netvlad, vlad, bow"):
        parse_options({"query_folder": "night", "reference_folders": "day", "descriptor": "cosplace"})
