"""Nearest-neighbour matching with hloc's rule, for float (L2) and binary (Hamming) descriptors."""

from __future__ import annotations

import ctypes
import functools
import importlib.util
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import torch

from gvbench_nb import GVBenchError
from gvbench_nb.protocol import registry
from gvbench_nb.protocol.matching.base import Matcher, Matches, empty_matches


def nearest_neighbour_matches(
    descriptors0: np.ndarray,
    descriptors1: np.ndarray,
    mutual: bool = True,
    ratio_threshold: float | None = None,
    distance_threshold: float | None = None,
    metric: str = "l2",
    ratio_test_on: str = "rows_and_columns",
    device: torch.device | str = "cpu",
) -> Matches:
    """Nearest-neighbour matches with hloc's rule (``hloc/matchers/nearest_neighbor.py``):
    ``l2`` through ``two_way_l2_matches`` (on ``device``), ``hamming`` (binary uint8 descriptors)
    through ``hamming_nearest_neighbour_matches``. Returns (matches (M, 2) int64, scores (M,) float32)."""
    check_ratio_test_on(ratio_test_on)
    registry.check_choice("metric", metric, ("l2", "hamming"))
    if metric == "hamming":
        return hamming_nearest_neighbour_matches(
            descriptors0, descriptors1, mutual, ratio_threshold, distance_threshold, ratio_test_on
        )
    matches, scores = two_way_l2_matches(
        torch.as_tensor(descriptors0).to(device),
        torch.as_tensor(descriptors1).to(device),
        mutual,
        ratio_threshold,
        distance_threshold,
        ratio_test_on,
    )
    return matches.numpy().astype(np.int64), scores.numpy().astype(np.float32)


# Where the Lowe ratio test applies under the mutual check: hloc applies it to the rows AND the
# columns (the paper's chain); "rows" is the one-way reading (ratio on the rows, then only the
# mutual check), kept so that what the two-way test changes can be measured.
RATIO_TEST_ON = ("rows_and_columns", "rows")


def check_ratio_test_on(ratio_test_on: str) -> None:
    registry.check_choice("ratio_test_on", ratio_test_on, RATIO_TEST_ON)


# The compiled kernel (kernels/hamming.c, built by `make setup` or `pip install -e .`): its
# instruction sets, widest last; the tests cap the choice to run each path.
HAMMING_INSTRUCTION_SETS = ("portable", "popcount", "avx512")
HAMMING_KERNEL = "gvbench_nb.protocol.matching.kernels.hamming"


class KernelNotBuiltError(GVBenchError, RuntimeError):
    """The checkout's compiled Hamming kernel is missing (set-up not run since it was cloned or changed)."""


@functools.cache
def hamming_kernel() -> ctypes.CDLL:
    """The Hamming kernel's shared library, loaded once; one sentence if it is not built."""
    spec = importlib.util.find_spec(HAMMING_KERNEL)
    if spec is None or spec.origin is None:
        folder = Path(__file__).parent / "kernels"
        raise KernelNotBuiltError(
            f"the Hamming matcher's kernel is not built in {folder}: run `make setup` (or `pip install -e .`) "
            "in the repository, with gcc or clang installed"
        )
    library = ctypes.CDLL(spec.origin)
    pointer, count = ctypes.c_void_p, ctypes.c_int64
    library.hamming_two_nearest.argtypes = [pointer, pointer, count, count, count, *[pointer] * 7, ctypes.c_int]
    library.hamming_two_nearest.restype = None
    library.hamming_instruction_set.argtypes = [ctypes.c_int]
    library.hamming_instruction_set.restype = ctypes.c_int
    return library


TwoNearest = tuple[np.ndarray, np.ndarray, np.ndarray]


def hamming_two_nearest(
    descriptors0: np.ndarray, descriptors1: np.ndarray, columns: bool = True, widest: str = "avx512"
) -> tuple[TwoNearest, TwoNearest | None]:
    """Each row's and (with ``columns``) each column's nearest index, smallest and second-smallest
    Hamming distance of non-empty uint8 (N, B) binary descriptors, as ``_two_nearest`` gives them on
    the distance matrix and its transpose (ties to the lower index; float64 distances, +inf second
    with one candidate). The kernel computes each distance once; rows are spread over OpenCV's
    thread count (ctypes releases the GIL), each thread's columns merged in row order."""
    library = hamming_kernel()
    instruction_set = library.hamming_instruction_set(HAMMING_INSTRUCTION_SETS.index(widest))
    words0, words1 = _words(descriptors0), _words(descriptors1)
    n0, n1, n_words = len(words0), len(words1), words0.shape[1]
    row = np.empty((3, n0), np.int32)
    threads = max(1, min(cv2.getNumThreads(), n0 // 256))
    bounds = np.linspace(0, n0, threads + 1).astype(int)
    column = np.empty((threads, 3, n1 if columns else 0), np.int32)

    def run(part: int) -> None:
        start = bounds[part]
        outputs: list[int | None] = [row[k, start:].ctypes.data for k in range(3)]
        outputs += [column[part, k].ctypes.data if columns else None for k in range(3)]
        scratch = np.empty(n1, np.int32)
        rows, n_rows = words0[start:].ctypes.data, bounds[part + 1] - start
        library.hamming_two_nearest(
            rows, words1.ctypes.data, n_rows, n1, n_words, scratch.ctypes.data, *outputs, instruction_set
        )

    if threads == 1:
        run(0)
    else:
        with ThreadPoolExecutor(max_workers=threads) as pool:
            list(pool.map(run, range(threads)))
    row_result = _as_two_nearest(row, n1)
    if not columns:
        return row_result, None
    nearest, first, second = column[0]
    for part in range(1, threads):
        # The two smallest of two disjoint sets: the smaller first, then the larger first or the
        # winner's second; a later part wins strictly only, so ties keep the lower row.
        part_nearest, part_first, part_second = column[part]
        second = np.minimum(np.minimum(second, part_second), np.maximum(first, part_first))
        nearest = np.where(part_first < first, part_nearest + bounds[part], nearest)
        first = np.minimum(first, part_first)
    return row_result, _as_two_nearest(np.stack([nearest, first, second]), n0)


def _words(descriptors: np.ndarray) -> np.ndarray:
    """uint8 (N, B) descriptors as (N, ceil(B / 8)) contiguous uint64 words, zero-padded."""
    descriptors = np.ascontiguousarray(descriptors, dtype=np.uint8)
    padded = -descriptors.shape[1] % 8
    if padded:
        descriptors = np.pad(descriptors, ((0, 0), (0, padded)))
    return descriptors.view(np.uint64)


def _as_two_nearest(result: np.ndarray, n_candidates: int) -> TwoNearest:
    second = result[2].astype(np.float64) if n_candidates > 1 else np.full(result.shape[1], np.inf)
    return result[0].astype(np.int64), result[1].astype(np.float64), second


def _two_nearest(distance: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each row's nearest column (the first of equal distances), its distance and the
    second-smallest distance in the row (equal to the first on a tie; +inf with one column)."""
    rows = np.arange(len(distance))
    nearest = distance.argmin(axis=1)
    first = distance[rows, nearest].astype(np.float64)
    if distance.shape[1] < 2:
        return nearest, first, np.full(len(distance), np.inf)
    others = distance.copy()
    others[rows, nearest] = np.iinfo(distance.dtype).max if distance.dtype.kind in "iu" else np.inf
    return nearest, first, others.min(axis=1).astype(np.float64)


def _passes(
    first: np.ndarray, second: np.ndarray, ratio_threshold: float | None, distance_threshold: float | None
) -> np.ndarray:
    """hloc's tests on one direction's two nearest distances (squared, as hloc compares them)."""
    keep = np.ones(len(first), bool)
    if ratio_threshold:
        keep &= first**2 <= ratio_threshold**2 * second**2
    if distance_threshold:
        keep &= first**2 <= distance_threshold**2
    return keep


def hamming_nearest_neighbour_matches(
    descriptors0: np.ndarray,
    descriptors1: np.ndarray,
    mutual: bool = True,
    ratio_threshold: float | None = None,
    distance_threshold: float | None = None,
    ratio_test_on: str = "rows_and_columns",
) -> Matches:
    """hloc's rule (``two_way_l2_matches``) on binary descriptors (uint8 (N, B)) by Hamming distance;
    ties go to the lower index. Scores are 1 - distance / bits."""
    if len(descriptors0) == 0 or len(descriptors1) == 0:
        return empty_matches()
    if min(len(descriptors0), len(descriptors1)) == 1:
        ratio_threshold = None
    (nearest1, first, second), columns = hamming_two_nearest(descriptors0, descriptors1, columns=mutual)
    keep = _passes(first, second, ratio_threshold, distance_threshold)
    if columns is not None:
        nearest0, first_back, second_back = columns
        column_ratio = ratio_threshold if ratio_test_on == "rows_and_columns" else None
        back = np.where(_passes(first_back, second_back, column_ratio, distance_threshold), nearest0, -1)
        keep &= back[nearest1] == np.arange(len(descriptors0))
    index0 = np.flatnonzero(keep)
    matches = np.stack([index0, nearest1[index0]], axis=1).astype(np.int64)
    n_bits = 8 * descriptors0.shape[1]
    return matches, (1 - first[index0] / n_bits).astype(np.float32)


def two_way_l2_matches(
    descriptors0: torch.Tensor,
    descriptors1: torch.Tensor,
    mutual: bool = True,
    ratio_threshold: float | None = None,
    distance_threshold: float | None = None,
    ratio_test_on: str = "rows_and_columns",
) -> tuple[torch.Tensor, torch.Tensor]:
    """hloc's nearest-neighbour rule (``hloc/matchers/nearest_neighbor.py``) on L2 descriptors:
    Lowe ratio (skipped for a single descriptor; ``ratio_test_on="rows"`` skips the columns'),
    distance test, optional ``mutual``; score (similarity + 1) / 2."""
    if len(descriptors0) == 0 or len(descriptors1) == 0:
        return torch.zeros((0, 2), dtype=torch.long), torch.zeros((0,))
    # hloc takes the product of the stored descriptors, which are unit vectors up to their
    # float16 rounding; normalising here makes any extractor's descriptors directions.
    descriptors0 = torch.nn.functional.normalize(descriptors0.float(), dim=1)
    descriptors1 = torch.nn.functional.normalize(descriptors1.float(), dim=1)
    similarity = descriptors0 @ descriptors1.T
    if len(descriptors0) == 1 or len(descriptors1) == 1:
        ratio_threshold = None

    def passes(best: torch.Tensor, second: torch.Tensor | None, ratio: float | None = ratio_threshold) -> torch.Tensor:
        distance_squared = 2 * (1 - best)
        keep = torch.ones_like(best, dtype=torch.bool)
        if ratio:
            assert second is not None, "second bests are computed whenever ratio_threshold is set"
            keep &= distance_squared <= ratio**2 * (2 * (1 - second))
        if distance_threshold:
            keep &= distance_squared <= distance_threshold**2
        return keep

    # max/amax rather than topk: several times less time on CPU. max(dim) returns the first
    # maximum on ties, as argmax does.
    best_similarity, best_index = similarity.max(dim=1)
    index0 = torch.arange(len(descriptors0), device=similarity.device)
    if mutual:
        column_best_index = similarity.max(dim=0).indices
        # A mutual pair's entry is the best of its row and of its column: masking it makes
        # the row and the column maxima their second bests. Other rows are dropped anyway.
        candidate = column_best_index[best_index] == index0
        rows, columns = index0[candidate], best_index[candidate]
        best = best_similarity[candidate]
        row_second = column_second = None
        if ratio_threshold:
            similarity[rows, columns] = -float("inf")
            row_second = similarity.amax(dim=1)[rows]
            column_second = similarity.amax(dim=0)[columns]
        column_ratio = ratio_threshold if ratio_test_on == "rows_and_columns" else None
        keep = passes(best, row_second) & passes(best, column_second, column_ratio)
    else:
        rows, columns, best = index0, best_index, best_similarity
        row_second = None
        if ratio_threshold:
            similarity[rows, columns] = -float("inf")
            row_second = similarity.amax(dim=1)
        keep = passes(best, row_second)
    matches = torch.stack([rows[keep], columns[keep]], dim=1)
    return matches.cpu(), ((best[keep] + 1) / 2).float().cpu()


# The rule a matcher conf applies: hloc's (above), or "knn_ratio", the GV-Bench repository's
# OpenCV matchers (image-matching-models' handcrafted.py): cv2.BFMatcher's two nearest neighbours
# of each row, kept when ``m.distance < ratio * n.distance``, no mutual check, raw descriptors.
RULES = ("hloc", "knn_ratio")


def check_rule(rule: str) -> None:
    registry.check_choice("nearest-neighbour rule", rule, RULES)


def l2_distances_as_opencv(descriptors0: np.ndarray, descriptors1: np.ndarray) -> np.ndarray:
    """(N0, N1) L2 distances as cv2.BFMatcher(NORM_L2) reports them (float32 roots); exact for
    OpenCV's whole-number SIFT descriptors, whose float64 product terms are integers."""
    a = np.asarray(descriptors0, dtype=np.float64)
    b = np.asarray(descriptors1, dtype=np.float64)
    squared = (a * a).sum(axis=1)[:, None] + (b * b).sum(axis=1)[None, :] - 2.0 * (a @ b.T)
    return np.sqrt(np.maximum(squared, 0.0).astype(np.float32))


# Whole, non-negative descriptors whose squared norms stay within 2^22 (OpenCV's SIFT: about
# 512^2 = 2^18) have products, norms and squared distances that are integers below 2^24: float32
# holds every partial sum exactly, whatever order the BLAS adds in.
EXACT_FLOAT32_SQUARED_NORM = float(1 << 22)


def exact_in_float32(descriptors: np.ndarray) -> bool:
    """Whether ``two_nearest_l2_as_opencv`` may take its float32 path for these descriptors."""
    if descriptors.size == 0 or descriptors.dtype.kind not in "fiu":
        return False
    values = np.asarray(descriptors, dtype=np.float32)
    return bool(
        values.min() >= 0
        and np.array_equal(values, np.rint(values))
        and np.einsum("ij,ij->i", values, values, dtype=np.float64).max() <= EXACT_FLOAT32_SQUARED_NORM
    )


def two_nearest_l2_as_opencv(
    descriptors0: np.ndarray, descriptors1: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each row's nearest column and two smallest distances as ``_two_nearest(l2_distances_as_opencv(...))``
    gives them; whole descriptors run exactly in float32 (argmax a.b - |b|^2 / 2, two roots a row;
    tied roots fail the ratio test anyway), others in float64."""
    if not (exact_in_float32(descriptors0) and exact_in_float32(descriptors1)) or len(descriptors1) < 2:
        return _two_nearest(l2_distances_as_opencv(descriptors0, descriptors1))
    a = np.asarray(descriptors0, dtype=np.float32)
    b = np.asarray(descriptors1, dtype=np.float32)
    half_norms1 = 0.5 * np.einsum("ij,ij->i", b, b)
    gain = a @ b.T
    gain -= half_norms1[None, :]
    rows = np.arange(len(a))
    nearest = gain.argmax(axis=1)
    best = gain[rows, nearest].astype(np.float64)
    gain[rows, nearest] = -np.inf
    runner_up = gain.max(axis=1).astype(np.float64)
    norms0 = np.einsum("ij,ij->i", a, a).astype(np.float64)

    def root(squared: np.ndarray) -> np.ndarray:
        return np.sqrt(np.maximum(squared, 0.0).astype(np.float32)).astype(np.float64)

    return nearest, root(norms0 - 2 * best), root(norms0 - 2 * runner_up)


class NearestNeighbourMatcher(Matcher):
    type = "nn"

    def __init__(self, conf: dict[str, Any], device: torch.device):
        check_ratio_test_on(conf.get("ratio_test_on", "rows_and_columns"))
        registry.check_choice("metric", conf.get("metric", "l2"), ("l2", "hamming"))
        check_rule(conf.get("rule", "hloc"))
        if conf.get("metric", "l2") == "hamming":
            hamming_kernel()  # refused here, before any pair, when the checkout was not set up
        if conf.get("rule", "hloc") == "knn_ratio" and (conf.get("mutual") or not conf.get("ratio_threshold")):
            raise ValueError(
                f"matcher conf {conf.get('name', '?')!r}: rule 'knn_ratio' is a one-way ratio test; "
                "set mutual: false and a ratio_threshold"
            )
        self.conf, self.device = conf, device

    def knn_ratio(self, descriptors0: np.ndarray, descriptors1: np.ndarray) -> Matches:
        """The repository's OpenCV rule on raw descriptors (Hamming bits for binary ones, OpenCV's L2
        distance for float ones): each row's nearest column, kept when strictly below
        ``ratio_threshold`` times the second-nearest (float64, as Python compares OpenCV's float32;
        ties never pass; one column keeps nothing). Scores: 1 - distance / bits, or (cosine
        similarity + 1) / 2 (the repository applies no score filter)."""
        if len(descriptors0) == 0 or len(descriptors1) < 2:
            return empty_matches()
        hamming = self.conf.get("metric", "l2") == "hamming"
        if hamming:
            (nearest, first, second), _ = hamming_two_nearest(descriptors0, descriptors1, columns=False)
        else:
            nearest, first, second = two_nearest_l2_as_opencv(descriptors0, descriptors1)
        rows = np.flatnonzero(first < self.conf["ratio_threshold"] * second)
        matches = np.stack([rows, nearest[rows]], axis=1).astype(np.int64)
        if hamming:
            return matches, (1 - first[rows] / (8 * descriptors0.shape[1])).astype(np.float32)
        a = descriptors0[matches[:, 0]].astype(np.float64)
        b = descriptors1[matches[:, 1]].astype(np.float64)
        norms = np.maximum(np.linalg.norm(a, axis=1) * np.linalg.norm(b, axis=1), 1e-12)
        return matches, (((a * b).sum(axis=1) / norms + 1) / 2).astype(np.float32)

    def __call__(self, features0: dict[str, np.ndarray], features1: dict[str, np.ndarray]) -> Matches:
        if self.conf.get("rule", "hloc") == "knn_ratio":
            return self.knn_ratio(features0["descriptors"], features1["descriptors"])
        return nearest_neighbour_matches(
            features0["descriptors"],
            features1["descriptors"],
            mutual=self.conf.get("mutual", True),
            ratio_threshold=self.conf.get("ratio_threshold"),
            distance_threshold=self.conf.get("distance_threshold"),
            metric=self.conf.get("metric", "l2"),
            ratio_test_on=self.conf.get("ratio_test_on", "rows_and_columns"),
            device=self.device,
        )
