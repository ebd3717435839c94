"""Nearest-neighbour matching (L2, and Hamming by the compiled kernel) against brute-force
references of hloc's rules and of the repository's OpenCV rule (first index on ties)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import torch

from gvbench_nb.protocol.matching import nearest_neighbour
from gvbench_nb.protocol.matching.nearest_neighbour import (
    HAMMING_INSTRUCTION_SETS,
    NearestNeighbourMatcher,
    hamming_nearest_neighbour_matches,
    hamming_two_nearest,
    nearest_neighbour_matches,
)


def _passes(distances: np.ndarray, ratio: float | None, threshold: float | None) -> tuple[int, bool]:
    """Best index of one row of distances and whether it passes the ratio and distance tests."""
    best = int(np.argmin(distances))
    ok = True
    if ratio is not None and len(distances) > 1:
        ok &= bool(distances[best] ** 2 <= ratio**2 * np.sort(distances)[1] ** 2)
    if threshold is not None:
        ok &= bool(distances[best] ** 2 <= threshold**2)
    return best, ok


def hloc_matches(distance: np.ndarray, mutual: bool, ratio: float | None, threshold: float | None) -> np.ndarray:
    """hloc's rule (matchers/nearest_neighbor.py): every row of the distance matrix keeps its
    nearest column if that passes the tests; with ``mutual`` every column does the same over
    the rows, and a match needs the row's choice and the column's choice to point at each
    other. The ratio test needs two descriptors on both sides."""
    if min(distance.shape) == 1:
        ratio = None
    rows = [_passes(row, ratio, threshold) for row in distance]
    columns = [_passes(column, ratio, threshold) for column in distance.T]
    matches = []
    for i, (j, row_ok) in enumerate(rows):
        if not row_ok:
            continue
        if mutual and not (columns[j][1] and columns[j][0] == i):
            continue
        matches.append((i, j))
    return np.array(matches, dtype=np.int64).reshape(-1, 2)


def one_way_matches(distance: np.ndarray, mutual: bool, ratio: float | None, threshold: float | None) -> np.ndarray:
    """The tests applied to rows only, then the mutual check: the one-way reading
    (``ratio_test_on="rows"``), not hloc's."""
    matches = []
    for i, row in enumerate(distance):
        j, ok = _passes(row, ratio, threshold)
        if ok and (not mutual or int(np.argmin(distance[:, j])) == i):
            matches.append((i, j))
    return np.array(matches, dtype=np.int64).reshape(-1, 2)


def _unit(array: np.ndarray) -> np.ndarray:
    return array / np.linalg.norm(array, axis=1, keepdims=True)


def _l2_distance(descriptors0: np.ndarray, descriptors1: np.ndarray) -> np.ndarray:
    similarity = _unit(descriptors0.astype(np.float64)) @ _unit(descriptors1.astype(np.float64)).T
    return np.sqrt(np.clip(2 - 2 * similarity, 0, None))


def test_ratio_applies_to_columns_too_minimal_case():
    # Row a0 passes its ratio test against b0/b1, and a0-b0 is mutual; but column b0 has two
    # rows almost equally near (a0, a1), so its ratio test fails and hloc keeps no match.
    rows = np.array([[1, 0.04, 0], [1, -0.045, 0]], np.float32)
    columns = np.array([[1, 0, 0], [0, 0, 1]], np.float32)
    distance = _l2_distance(rows, columns)
    assert one_way_matches(distance, True, 0.8, None).tolist() == [[0, 0]]
    assert hloc_matches(distance, True, 0.8, None).shape == (0, 2)

    matches, scores = nearest_neighbour_matches(rows, columns, ratio_threshold=0.8)
    assert matches.shape == (0, 2) and scores.shape == (0,)
    one_way, _ = nearest_neighbour_matches(rows, columns, ratio_threshold=0.8, ratio_test_on="rows")
    assert one_way.tolist() == [[0, 0]]


@pytest.mark.parametrize("seed", range(3))
@pytest.mark.parametrize("metric", ["l2", "hamming"])
def test_ratio_is_two_way_as_hlocs_or_rows_only_one_way(seed, metric):
    # Many rows crowd near few columns, so columns often fail their own ratio test: hloc's rule
    # (the default) and the rows-only ablation (``ratio_test_on="rows"``) differ here.
    rng = np.random.default_rng(20 + seed)
    if metric == "l2":
        descriptors1 = rng.normal(size=(60, 16)).astype(np.float32)
        parents = rng.integers(0, 60, 200)
        descriptors0 = (descriptors1[parents] + 0.35 * rng.normal(size=(200, 16))).astype(np.float32)
        distance = _l2_distance(descriptors0, descriptors1)
    else:
        descriptors1 = rng.integers(0, 256, (60, 32), dtype=np.uint8)
        flips = rng.random((200, 256)) < 0.15
        descriptors0 = np.packbits(np.unpackbits(descriptors1[rng.integers(0, 60, 200)], axis=1) ^ flips, axis=1)
        distance = bit_distances(descriptors0, descriptors1)
    two_way, one_way = hloc_matches(distance, True, 0.8, None), one_way_matches(distance, True, 0.8, None)
    assert len(one_way) > len(two_way) > 5

    def ours(rows: np.ndarray, columns: np.ndarray, **options) -> np.ndarray:
        return nearest_neighbour_matches(rows, columns, ratio_threshold=0.8, metric=metric, **options)[0]

    np.testing.assert_array_equal(ours(descriptors0, descriptors1), two_way)
    np.testing.assert_array_equal(ours(descriptors0, descriptors1, ratio_test_on="rows"), one_way)
    # And the other way round: image 1's descriptors as rows.
    np.testing.assert_array_equal(ours(descriptors1, descriptors0), hloc_matches(distance.T, True, 0.8, None))


@pytest.mark.parametrize(
    ("option", "message"),
    [({"ratio_test_on": "columns"}, "ratio_test_on"), ({"metric": "cosine"}, "unknown metric 'cosine'")],
)
def test_unknown_option_values_are_named(option, message):
    with pytest.raises(ValueError, match=message):
        nearest_neighbour_matches(np.ones((2, 4)), np.ones((2, 4)), ratio_threshold=0.8, **option)


RULES = [
    (True, 0.8, None),
    (True, None, None),
    (False, 0.8, None),
    (True, 0.9, 0.7),
    (False, None, None),
    (True, None, 0.9),
]


@pytest.mark.parametrize("mutual, ratio, threshold", RULES)
def test_l2_matches_equal_hloc_rule_with_duplicated_descriptors(mutual, ratio, threshold):
    rng = np.random.default_rng(1)
    descriptors0 = rng.normal(size=(300, 32)).astype(np.float32)
    descriptors1 = np.concatenate(
        [descriptors0[:120] + 0.3 * rng.normal(size=(120, 32)), rng.normal(size=(100, 32))]
    ).astype(np.float32)
    descriptors0[50] = descriptors0[10]  # identical descriptors tie on every column
    descriptors1[7] = descriptors1[3]
    distance = _l2_distance(descriptors0, descriptors1)
    expected = hloc_matches(distance, mutual, ratio, threshold)

    matches, scores = nearest_neighbour_matches(
        descriptors0, descriptors1, mutual=mutual, ratio_threshold=ratio, distance_threshold=threshold
    )

    assert len(expected) > 20  # the case is not vacuous
    np.testing.assert_array_equal(matches, expected)
    similarity = 1 - distance[expected[:, 0], expected[:, 1]] ** 2 / 2
    np.testing.assert_allclose(scores, (similarity + 1) / 2, atol=1e-5)
    if mutual:
        assert len(np.unique(matches[:, 1])) == len(matches)  # one-to-one despite the duplicates


def test_empty_and_single_column_inputs():
    empty, _ = nearest_neighbour_matches(np.zeros((0, 8)), np.ones((5, 8)), ratio_threshold=0.8)
    assert empty.shape == (0, 2)
    # One reference descriptor: the ratio test has no second neighbour and is skipped.
    eye = np.eye(3, dtype=np.float32)
    matches, _ = nearest_neighbour_matches(eye, eye[:1], ratio_threshold=0.8)
    np.testing.assert_array_equal(matches, [[0, 0]])
    # hloc skips it when either image has one descriptor, even where image 1 has two near ones.
    near_pair = np.array([[1.0, 0.0, 0.0], [0.99, 0.14, 0.0]], np.float32)
    matches, _ = nearest_neighbour_matches(eye[:1], near_pair, ratio_threshold=0.8)
    np.testing.assert_array_equal(matches, [[0, 0]])
    distance = _l2_distance(eye[:1], near_pair)
    np.testing.assert_array_equal(hloc_matches(distance, True, 0.8, None), [[0, 0]])
    # The same on binary descriptors (Hamming).
    binary0 = np.random.default_rng(3).integers(0, 256, (20, 32), dtype=np.uint8)
    one = binary0[4:5] ^ np.uint8(1)
    for mutual in (True, False):
        for rows, columns in ((binary0, one), (one, binary0)):
            matches, _ = hamming_nearest_neighbour_matches(rows, columns, mutual=mutual, ratio_threshold=0.8)
            np.testing.assert_array_equal(matches, hloc_matches(bit_distances(rows, columns), mutual, 0.8, None))
    matches, scores = hamming_nearest_neighbour_matches(binary0[:0], binary0, ratio_threshold=0.8)
    assert matches.shape == (0, 2) and scores.shape == (0,)
    assert hamming_nearest_neighbour_matches(binary0, binary0[:0])[0].shape == (0, 2)


# hloc/match_features.py (the authors' fork, gvbench@427cc99) as (mutual, ratio, distance):
# L46-53 confs["NN-superpoint"], L54-61 confs["NN-ratio"], L62-68 confs["NN-mutual"]. The
# repository's xfeat-nn is XFeat.match(min_cossim=-1) (the fork's xfeat.py:L51): mutual nearest
# neighbours, every similarity accepted, which is NN-mutual's rule.
HLOC_NN_CONFS = {"NN-superpoint": (True, None, 0.7), "NN-ratio": (True, 0.8, None), "NN-mutual": (True, None, None)}
NN_RECIPES = [
    ("paper", "sift-nn", "NN-ratio"),
    ("paper", "disk-nn", "NN-ratio"),
    ("paper", "sift-opencv-nn", "NN-ratio"),
    ("paper", "sp-nn", "NN-superpoint"),
    ("repository", "sp-nn", "NN-superpoint"),
    ("paper", "aliked-nn", "NN-mutual"),
    ("paper", "xfeat-nn", "NN-mutual"),
    ("repository", "aliked-nn", "NN-mutual"),
    ("repository", "xfeat-nn", "NN-mutual"),
]


@pytest.mark.parametrize("profile, method, hloc_conf", NN_RECIPES)
def test_nn_recipes_match_as_hlocs_confs(profile, method, hloc_conf):
    """Each NN recipe's matcher gives hloc's matches under the conf it names, on descriptors
    where another ratio (0.75, 0.85), distance (0.65, 0.75) or no mutual check gives others."""
    from gvbench_nb import methods
    from gvbench_nb.protocol.matching import build_matcher

    rng = np.random.default_rng(5)
    descriptors1 = _unit(rng.normal(size=(80, 16))).astype(np.float32)
    parents = rng.integers(0, 80, 160)
    descriptors0 = _unit(descriptors1[parents] + 0.2 * rng.normal(size=(160, 16))).astype(np.float32)
    distance = _l2_distance(descriptors0, descriptors1)
    mutual, ratio, threshold = HLOC_NN_CONFS[hloc_conf]
    expected = hloc_matches(distance, mutual, ratio, threshold)
    assert len(expected) > 10
    others = [(False, ratio, threshold)]
    others += [(mutual, r, threshold) for r in (0.75, 0.85) if ratio is not None]
    others += [(mutual, ratio, d) for d in (0.65, 0.75) if threshold is not None]
    for other in others:
        assert not np.array_equal(hloc_matches(distance, *other), expected), other

    matcher = build_matcher(methods.resolve_method(method, profile)["matcher"], torch.device("cpu"))
    matches, _ = matcher({"descriptors": descriptors0}, {"descriptors": descriptors1})
    np.testing.assert_array_equal(matches, expected)


# ------------------------------------------------------------------ Hamming --
def bit_distances(binary0: np.ndarray, binary1: np.ndarray) -> np.ndarray:
    """Full Hamming distance matrix from unpacked bits, no popcount involved."""
    bits0, bits1 = np.unpackbits(binary0, axis=1), np.unpackbits(binary1, axis=1)
    return (bits0[:, None, :] != bits1[None, :, :]).sum(-1).astype(np.float64)


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
HAMMING_RULES = [
    (True, 0.8, None),
    (True, None, None),
    (False, 0.8, None),
    (True, 0.9, 0.15),
    (False, None, None),
    (True, None, 0.11),
]


@pytest.mark.parametrize("mutual, ratio, threshold", HAMMING_RULES)
@pytest.mark.parametrize("make, n_bytes", [(tie_heavy, 8), (tie_heavy, 32), (near_copies, 32), (near_copies, 8)])
def test_hamming_matches_equal_brute_force(make, n_bytes, mutual, ratio, threshold):
    threshold = threshold and threshold * 8 * n_bytes
    rng = np.random.default_rng(n_bytes)
    binary0, binary1 = make(rng, 300, 260, n_bytes)
    distance = bit_distances(binary0, binary1)
    expected = hloc_matches(distance, mutual, ratio, threshold)

    matches, scores = hamming_nearest_neighbour_matches(
        binary0, binary1, mutual=mutual, ratio_threshold=ratio, distance_threshold=threshold
    )

    assert len(expected) > 5  # the case is not vacuous
    np.testing.assert_array_equal(matches, expected)
    assert matches.dtype == np.int64 and scores.dtype == np.float32
    np.testing.assert_allclose(scores, 1 - distance[expected[:, 0], expected[:, 1]] / (8 * n_bytes), atol=1e-6)
    if mutual:
        assert len(np.unique(matches[:, 1])) == len(matches)  # one-to-one despite the duplicates


def two_nearest_by_sorting(distance: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each row's nearest column (the lowest index of its smallest distance: a stable sort),
    smallest and second-smallest distance (+inf with one column)."""
    order = np.argsort(distance, axis=1, kind="stable")
    rows = np.arange(len(distance))
    second = distance[rows, order[:, 1]] if distance.shape[1] > 1 else np.full(len(distance), np.inf)
    return order[:, 0], distance[rows, order[:, 0]], second


@pytest.mark.parametrize("widest", HAMMING_INSTRUCTION_SETS)
@pytest.mark.parametrize("n_bytes, threads", [(32, 1), (32, 3), (8, 2), (5, 1), (1, 2), (61, 1)])
def test_hamming_two_nearest_of_rows_and_columns_equal_sorted_bit_distances(widest, n_bytes, threads):
    """The kernel's one pass gives each row's and each column's nearest index and two smallest
    distances, ties to the lower index, on every instruction set this CPU runs (``widest`` caps
    it), any descriptor length (padded to 64-bit words) and rows split over threads."""
    rng = np.random.default_rng(n_bytes + threads)
    binary0, binary1 = tie_heavy(rng, 256 * threads + 7, 300, n_bytes)
    distance = bit_distances(binary0, binary1)
    before = cv2.getNumThreads()
    cv2.setNumThreads(threads)
    try:
        rows, columns = hamming_two_nearest(binary0, binary1, widest=widest)
        rows_only, no_columns = hamming_two_nearest(binary0, binary1, columns=False, widest=widest)
    finally:
        cv2.setNumThreads(before)
    assert no_columns is None and columns is not None
    for got, expected in ((rows, two_nearest_by_sorting(distance)), (columns, two_nearest_by_sorting(distance.T))):
        for array, reference in zip(got, expected):
            np.testing.assert_array_equal(array, reference)
    for array, reference in zip(rows_only, rows):
        np.testing.assert_array_equal(array, reference)
    assert (rows[1] == rows[2]).sum() > 20 and (columns[1] == columns[2]).sum() > 20  # ties are tested


def opencv_knn_ratio(binary0: np.ndarray, binary1: np.ndarray, ratio: float = 0.75) -> tuple[np.ndarray, np.ndarray]:
    """The repository's rule as its fork runs it (``handcrafted.py`` L43-49): OpenCV's
    ``BFMatcher(NORM_HAMMING).knnMatch(k=2)``, kept when ``m.distance < ratio * n.distance``;
    scores 1 - distance / bits."""
    pairs = cv2.BFMatcher(cv2.NORM_HAMMING).knnMatch(binary0, binary1, k=2)
    kept = [m for m, n in pairs if m.distance < ratio * n.distance]
    matches = np.array([(m.queryIdx, m.trainIdx) for m in kept], np.int64).reshape(-1, 2)
    return matches, np.array([1 - m.distance / (8 * binary0.shape[1]) for m in kept], np.float32)


REPOSITORY_ORB_MATCHER = {"type": "nn", "metric": "hamming", "mutual": False, "ratio_threshold": 0.75}


@pytest.mark.parametrize("make, n_bytes", [(tie_heavy, 32), (tie_heavy, 8), (near_copies, 32)])
def test_the_repository_rule_on_hamming_equals_opencvs_knn_ratio(make, n_bytes):
    rng = np.random.default_rng(7 + n_bytes)
    binary0, binary1 = make(rng, 300, 260, n_bytes)
    matcher = NearestNeighbourMatcher({**REPOSITORY_ORB_MATCHER, "rule": "knn_ratio"}, torch.device("cpu"))
    matches, scores = matcher({"descriptors": binary0}, {"descriptors": binary1})
    expected, expected_scores = opencv_knn_ratio(binary0, binary1)
    assert len(expected) > 5
    np.testing.assert_array_equal(matches, expected)
    np.testing.assert_array_equal(scores, expected_scores)


def byte_table_distances(binary0: np.ndarray, binary1: np.ndarray) -> np.ndarray:
    """Hamming distances by a 256-entry table of byte popcounts, a block of rows at a time (real
    images' 2048 x 2048 x 256 bits would not fit ``bit_distances``'s boolean cube)."""
    table = np.array([bin(value).count("1") for value in range(256)], np.int64)
    blocks = [table[block[:, None, :] ^ binary1[None, :, :]].sum(-1) for block in np.array_split(binary0, 32)]
    return np.concatenate(blocks).astype(np.float64)


@pytest.mark.real_data
@pytest.mark.slow
@pytest.mark.parametrize("profile", ["paper", "repository"])
def test_orb_nn_matches_real_gardens_point_pairs_as_the_references(shared_data, profile):
    """orb-nn's recipe matcher on ORB features of Gardens Point images, extracted by the package:
    hloc's two-way ratio rule (``paper``) or OpenCV's knn ratio (``repository``), match for match."""
    from gvbench_nb import methods
    from gvbench_nb.protocol import images
    from gvbench_nb.protocol.features import build_extractor
    from gvbench_nb.protocol.matching import build_matcher

    conf = methods.resolve_method("orb-nn", profile)
    extractor = build_extractor(conf["extractor"], torch.device("cpu"))
    root = shared_data / "gardens_point"

    def descriptors(name: str) -> np.ndarray:
        image, _ = images.load_for_extraction(root / name, conf["extractor"])
        return np.asarray(extractor(image)["descriptors"])

    # A night query (few matches) and a day frame near references 40 and 41 (many).
    queries = [descriptors(name) for name in ("night_right/Image040.jpg", "day_right/Image042.jpg")]
    references = [descriptors(f"day_right/Image{r:03d}.jpg") for r in (40, 41, 100)]
    matcher = build_matcher(conf["matcher"], torch.device("cpu"))
    n_matches = 0
    for query in queries:
        for reference in references:
            matches, scores = matcher({"descriptors": query}, {"descriptors": reference})
            if profile == "paper":
                distance = byte_table_distances(query, reference)
                expected = hloc_matches(distance, True, 0.8, None)
                expected_scores = 1 - distance[expected[:, 0], expected[:, 1]] / 256
            else:
                expected, expected_scores = opencv_knn_ratio(query, reference)
            np.testing.assert_array_equal(matches, expected)
            np.testing.assert_allclose(scores, expected_scores, rtol=0, atol=1e-7)
            n_matches += len(expected)
    assert min(map(len, queries + references)) > 1000 and n_matches > 100


@pytest.mark.reliability
def test_a_missing_hamming_kernel_is_one_sentence_naming_the_setup(monkeypatch, capsys, root, tmp_path):
    """A checkout whose kernel was never built (cloned, or changed, without `make setup`): a run of a
    Hamming method is refused before any work, in one sentence naming what to run; the matcher
    itself refuses too. L2 matching needs no kernel."""
    from helpers import PAIRS, assert_nothing_written, cli_error, write_params

    from gvbench_nb.data.sequences import write_pairs

    monkeypatch.setattr(nearest_neighbour, "HAMMING_KERNEL", "gvbench_nb.protocol.matching.kernels.absent")
    nearest_neighbour.hamming_kernel.cache_clear()
    try:
        write_pairs(tmp_path / "pairs.txt", PAIRS)
        params = write_params(tmp_path, image_root=str(root), methods=["orb-nn"])
        message = cli_error(capsys, "run", str(params))
        with pytest.raises(nearest_neighbour.KernelNotBuiltError, match="make setup"):
            NearestNeighbourMatcher(REPOSITORY_ORB_MATCHER, torch.device("cpu"))
    finally:
        nearest_neighbour.hamming_kernel.cache_clear()
    assert "Hamming matcher's kernel is not built" in message and "make setup" in message
    assert_nothing_written(tmp_path)
    NearestNeighbourMatcher({"type": "nn", "mutual": True}, torch.device("cpu"))


def test_hamming_ties_go_to_the_lower_index():
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


def test_the_nn_matcher_dispatches_hamming_here():
    rng = np.random.default_rng(4)
    binary0, binary1 = near_copies(rng, 120, 100, 32)
    conf = {"type": "nn", "metric": "hamming", "mutual": True, "ratio_threshold": 0.8}
    matches, scores = NearestNeighbourMatcher(conf, torch.device("cpu"))(
        {"descriptors": binary0}, {"descriptors": binary1}
    )
    expected = hloc_matches(bit_distances(binary0, binary1), True, 0.8, None)
    assert len(expected) > 20
    np.testing.assert_array_equal(matches, expected)
