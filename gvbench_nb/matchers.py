"""Matchers, one small class a type, selected by ``conf['type']``.

A sparse matcher takes two feature dicts (from the cache: keypoints in original
pixels, descriptors, ``image_size`` as (width, height)) and returns
``matches`` (M, 2) int64 indices into keypoints0/1 and ``scores`` (M,) float32.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any, Callable

import numpy as np
import torch

from . import weights

if TYPE_CHECKING:  # kornia is imported when a matcher is built, not when this module is
    from .models.lightglue_prepared import PreparedImage

Matches = tuple[np.ndarray, np.ndarray]


def _empty_matches() -> Matches:
    return np.zeros((0, 2), np.int64), np.zeros((0,), np.float32)


def nearest_neighbour_matches(
    descriptors0: torch.Tensor,
    descriptors1: torch.Tensor,
    mutual: bool = True,
    ratio_threshold: float | None = None,
    distance_threshold: float | None = None,
    metric: str = "l2",
) -> tuple[torch.Tensor, torch.Tensor]:
    """Nearest-neighbour matches with hloc's rule (``hloc/matchers/nearest_neighbor.py``):
    ``l2`` through ``two_way_l2_matches``, ``hamming`` (binary uint8 descriptors) through
    ``hamming_nearest_neighbour_matches``. Returns (matches (M, 2) long, scores (M,) float)."""
    if metric == "l2":
        return two_way_l2_matches(descriptors0, descriptors1, mutual, ratio_threshold, distance_threshold)
    if metric == "hamming":
        matches, scores = hamming_nearest_neighbour_matches(
            descriptors0.cpu().numpy(), descriptors1.cpu().numpy(), mutual, ratio_threshold, distance_threshold)
        return torch.from_numpy(matches), torch.from_numpy(scores)
    raise ValueError(f"unknown metric {metric!r}; use 'l2' or 'hamming'")


def hamming_distances(descriptors0: np.ndarray, descriptors1: np.ndarray, rows_per_block: int = 64) -> np.ndarray:
    """(N0, N1) uint16 Hamming distances of uint8 (N, B) binary descriptors, by popcount.

    The bytes are read as 64-bit words (zero-padded: padding adds no differing bits) and
    ``np.bitwise_count`` counts the bits of their XOR; rows go in blocks so that the temporary
    word matrix stays at ``rows_per_block * N1`` words (cache-sized) whatever the number of descriptors.
    """
    n_bytes = descriptors0.shape[1]
    padded = -n_bytes % 8

    def words(descriptors: np.ndarray) -> np.ndarray:
        descriptors = np.ascontiguousarray(descriptors, dtype=np.uint8)
        if padded:
            descriptors = np.pad(descriptors, ((0, 0), (0, padded)))
        return descriptors.view(np.uint64)

    words0, words1 = words(descriptors0), words(descriptors1)
    distance = np.empty((len(words0), len(words1)), np.uint16)
    for start in range(0, len(words0), rows_per_block):
        block = distance[start:start + rows_per_block]
        block[:] = 0
        for word in range(words0.shape[1]):
            block += np.bitwise_count(words0[start:start + rows_per_block, word, None] ^ words1[None, :, word])
    return distance


def _two_nearest(distance: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each row's nearest column (the first of equal distances), its distance and the
    second-smallest distance in the row (equal to the first on a tie; +inf with one column)."""
    rows = np.arange(len(distance))
    nearest = distance.argmin(axis=1)
    first = distance[rows, nearest].astype(np.float64)
    if distance.shape[1] < 2:
        return nearest, first, np.full(len(distance), np.inf)
    others = distance.copy()
    others[rows, nearest] = np.iinfo(distance.dtype).max
    return nearest, first, others.min(axis=1).astype(np.float64)


def _passes(first: np.ndarray, second: np.ndarray, ratio_threshold: float | None,
            distance_threshold: float | None) -> np.ndarray:
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
) -> Matches:
    """Nearest-neighbour matches of binary descriptors (uint8 (N, B), 8B bits) by Hamming distance,
    with hloc's rule (``hloc/matchers/nearest_neighbor.py``): each row's nearest column must pass
    the Lowe ratio (d1 <= ratio * d2) and the distance threshold; with ``mutual``, that column's
    nearest row, under the same tests, must be the row itself. The ratio test is skipped when
    either side has a single descriptor. Ties go to the lower index: the nearest is the first
    minimum, and a tie at the nearest distance fails the ratio test unless both are 0 bits.
    Returns matches (M, 2) int64 and scores (M,) float32 = 1 - distance / bits.
    """
    if len(descriptors0) == 0 or len(descriptors1) == 0:
        return _empty_matches()
    if min(len(descriptors0), len(descriptors1)) == 1:
        ratio_threshold = None
    distance = hamming_distances(descriptors0, descriptors1)
    nearest1, first, second = _two_nearest(distance)
    keep = _passes(first, second, ratio_threshold, distance_threshold)
    if mutual:
        nearest0, first_back, second_back = _two_nearest(distance.T)
        back = np.where(_passes(first_back, second_back, ratio_threshold, distance_threshold), nearest0, -1)
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
) -> tuple[torch.Tensor, torch.Tensor]:
    """hloc's nearest-neighbour rule (``hloc/matchers/nearest_neighbor.py``) on L2 descriptors.

    Similarity = dot product of the L2-normalised descriptors, distance^2 = 2 (1 - similarity).
    Each row (a descriptor of image 0) keeps its best column when it passes the Lowe ratio
    (d1^2 <= ratio^2 d2^2, d1 and d2 its two best) and the distance test (d1 <= threshold);
    with ``mutual`` each column (a descriptor of image 1) must pass the same tests against
    its two best rows, and the row and column must be each other's best. The ratio test is
    skipped when either image has a single descriptor. Score = (similarity + 1) / 2. Ties
    go to the first index. Returns (matches (M, 2) long, scores (M,) float).
    """
    if len(descriptors0) == 0 or len(descriptors1) == 0:
        return torch.zeros((0, 2), dtype=torch.long), torch.zeros((0,))
    # hloc takes the product of the stored descriptors, which are unit vectors up to their
    # float16 rounding; normalising here makes any extractor's descriptors directions.
    descriptors0 = torch.nn.functional.normalize(descriptors0.float(), dim=1)
    descriptors1 = torch.nn.functional.normalize(descriptors1.float(), dim=1)
    similarity = descriptors0 @ descriptors1.T
    if len(descriptors0) == 1 or len(descriptors1) == 1:
        ratio_threshold = None

    def passes(best: torch.Tensor, second: torch.Tensor | None) -> torch.Tensor:
        distance_squared = 2 * (1 - best)
        keep = torch.ones_like(best, dtype=torch.bool)
        if ratio_threshold:
            keep &= distance_squared <= ratio_threshold**2 * (2 * (1 - second))
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
        keep = passes(best, row_second) & passes(best, column_second)
    else:
        rows, columns, best = index0, best_index, best_similarity
        row_second = None
        if ratio_threshold:
            similarity[rows, columns] = -float("inf")
            row_second = similarity.amax(dim=1)
        keep = passes(best, row_second)
    matches = torch.stack([rows[keep], columns[keep]], dim=1)
    return matches.cpu(), ((best[keep] + 1) / 2).float().cpu()


class NearestNeighbourMatcher:
    def __init__(self, conf: dict[str, Any], device: torch.device):
        self.conf, self.device = conf, device

    def __call__(self, features0: dict[str, np.ndarray], features1: dict[str, np.ndarray]) -> Matches:
        if self.conf.get("metric", "l2") == "hamming":
            return hamming_nearest_neighbour_matches(
                features0["descriptors"], features1["descriptors"], mutual=self.conf.get("mutual", True),
                ratio_threshold=self.conf.get("ratio_threshold"), distance_threshold=self.conf.get("distance_threshold"),
            )
        matches, scores = nearest_neighbour_matches(
            torch.from_numpy(features0["descriptors"]).to(self.device),
            torch.from_numpy(features1["descriptors"]).to(self.device),
            mutual=self.conf.get("mutual", True),
            ratio_threshold=self.conf.get("ratio_threshold"),
            distance_threshold=self.conf.get("distance_threshold"),
            metric=self.conf.get("metric", "l2"),
        )
        return matches.numpy().astype(np.int64), scores.numpy().astype(np.float32)


class LightGlueMatcher:
    """kornia LightGlue (and LighterGlue for XFeat) with the paper's thresholds."""

    def __init__(self, conf: dict[str, Any], device: torch.device):
        from kornia.feature import LightGlue

        from .models import lightglue_prepared

        self._prepared = lightglue_prepared
        weights.require(*conf["checkpoints"])
        self.device = device
        options = {k: conf[k] for k in ("depth_confidence", "width_confidence", "filter_threshold") if k in conf}
        self.model = LightGlue(conf["features"], **options).to(device).eval()
        # The per-image part of LightGlue can be computed once per image (models/lightglue_prepared.py);
        # that split reproduces the CPU path only.
        self.can_prepare = device.type == "cpu" and lightglue_prepared.supports_prepared(self.model)
        # 'kornia' (default): kornia's CPU cross-attention, bit-identical to LightGlue.forward.
        # 'sdpa': torch's fused attention kernel on that path, equal up to float rounding.
        # On CUDA kornia's own forward already attends through scaled_dot_product_attention.
        self.cross_attention = conf.get("cross_attention", "kornia")
        if self.cross_attention not in lightglue_prepared.CROSS_ATTENTIONS:
            raise ValueError(f"matcher {conf.get('name', conf['type'])!r}: unknown cross_attention "
                             f"{self.cross_attention!r}; use one of {', '.join(lightglue_prepared.CROSS_ATTENTIONS)}")
        if self.cross_attention == "sdpa" and device.type == "cpu" and not self.can_prepare:
            raise ValueError(f"matcher {conf.get('name', conf['type'])!r}: cross_attention 'sdpa' needs the prepared "
                             "CPU path (no mixed precision, scale/orientation or LAF inputs); drop the option")

    def _side(self, features: dict[str, np.ndarray]) -> dict[str, torch.Tensor]:
        return {
            "keypoints": torch.from_numpy(features["keypoints"]).float()[None].to(self.device),
            "descriptors": torch.from_numpy(features["descriptors"]).float()[None].to(self.device),
            "image_size": torch.from_numpy(features["image_size"]).float()[None].to(self.device),
        }

    @torch.inference_mode()
    def __call__(self, features0: dict[str, np.ndarray], features1: dict[str, np.ndarray]) -> Matches:
        if len(features0["keypoints"]) == 0 or len(features1["keypoints"]) == 0:
            return _empty_matches()
        output = self.model({"image0": self._side(features0), "image1": self._side(features1)})
        return (
            output["matches"][0].cpu().numpy().astype(np.int64),
            output["scores"][0].cpu().numpy().astype(np.float32),
        )

    def prepare(self, features: dict[str, np.ndarray]) -> PreparedImage | None:
        """One image's LightGlue state before it meets the other image (None: no keypoints)."""
        if not self.can_prepare:
            raise RuntimeError("this LightGlue cannot be prepared per image (CUDA, mixed precision or "
                               "scale/orientation inputs); call the matcher on two feature dicts")
        if len(features["keypoints"]) == 0:
            return None
        side = self._side(features)
        return self._prepared.prepare_image(self.model, side["keypoints"], side["descriptors"], side["image_size"])

    def match_prepared(self, prepared0: PreparedImage | None, prepared1: PreparedImage | None) -> Matches:
        """The same matches and scores as ``self(features0, features1)``, from ``prepare``'s states."""
        if prepared0 is None or prepared1 is None:
            return _empty_matches()
        pair_matches, scores = self._prepared.match_prepared(self.model, prepared0, prepared1, self.cross_attention)
        return pair_matches.cpu().numpy().astype(np.int64), scores.cpu().numpy().astype(np.float32)


class SuperGlueMatcher:
    """Our SuperGlue (``models/superglue.py``) on the official outdoor weights."""

    def __init__(self, conf: dict[str, Any], device: torch.device):
        from .models.superglue import load_superglue

        self.device = device
        model_conf = {k: conf[k] for k in ("sinkhorn_iterations", "match_threshold") if k in conf}
        self.model = load_superglue(model_conf, device=device).eval()

    @torch.inference_mode()
    def __call__(self, features0: dict[str, np.ndarray], features1: dict[str, np.ndarray]) -> Matches:
        if len(features0["keypoints"]) == 0 or len(features1["keypoints"]) == 0:
            return _empty_matches()
        data = {}
        for i, features in enumerate((features0, features1)):
            width, height = (int(v) for v in features["image_size"])
            data[f"keypoints{i}"] = torch.from_numpy(features["keypoints"]).float()[None].to(self.device)
            data[f"scores{i}"] = torch.from_numpy(features["scores"]).float()[None].to(self.device)
            data[f"descriptors{i}"] = torch.from_numpy(features["descriptors"]).float()[None].to(self.device)
            data[f"image_size{i}"] = (height, width)
        output = self.model(data)
        matches0 = output["matches0"][0].cpu().numpy()
        scores0 = output["matching_scores0"][0].cpu().numpy()
        valid = matches0 > -1
        matches = np.stack([np.nonzero(valid)[0], matches0[valid]], axis=1).astype(np.int64)
        return matches, scores0[valid].astype(np.float32)


def swapped_dense_call(model: Callable[[dict[str, torch.Tensor]], dict[str, torch.Tensor]],
                       image0: torch.Tensor, image1: torch.Tensor) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """LoFTR run as hloc runs it (``hloc/matchers/loftr.py``): the network sees image 1 as
    its first image and image 0 as its second (its fine stage refines the second image's
    points, so hloc's image 0 is the refined one); the points come back in our order.
    Returns (points in image 0, points in image 1, confidences)."""
    output = model({"image0": image1, "image1": image0})
    return (
        output["keypoints1"].cpu().numpy().astype(np.float32),
        output["keypoints0"].cpu().numpy().astype(np.float32),
        output["confidence"].cpu().numpy().astype(np.float32),
    )


class LoFTRMatcher:
    """kornia LoFTR run as a dense pair matcher (no per-image cache) with the paper's
    preprocessing: grayscale, longest side <= 1024, both sides floored to a multiple of 8.

    Takes two prepared grayscale images (float32, 0..255), runs them swapped as hloc does
    (``swapped_dense_call``) and returns points in their pixels and confidences; the
    pipeline merges them across pairs (``merge_dense_matches``). The official checkpoint
    is loaded here with ``weights_only=True``.
    """

    dense = True

    def __init__(self, conf: dict[str, Any], device: torch.device):
        from kornia.feature import LoFTR

        (path,) = weights.require(*conf["checkpoints"])
        self.device = device
        self.model = LoFTR(pretrained=None)
        self.model.coarse_matching.thr = conf.get("coarse_threshold", 0.2)
        checkpoint = weights.load_checkpoint(path)
        state_dict = checkpoint.get("state_dict", checkpoint)
        state_dict = {k.removeprefix("matcher."): v for k, v in state_dict.items()}
        weights.load_state_dict_strict(self.model, state_dict, str(path))
        self.model = self.model.to(device).eval()

    @torch.inference_mode()
    def __call__(self, image0: np.ndarray, image1: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        def tensor(image: np.ndarray) -> torch.Tensor:
            return torch.from_numpy(image).float().div(255.0)[None, None].to(self.device)

        return swapped_dense_call(self.model, tensor(image0), tensor(image1))


def _cell_centres(points: np.ndarray, size: float) -> np.ndarray:
    """hloc's quantisation (``match_dense.to_cpts``): the centre of each point's
    ``size``-pixel cell, np.round (half to even) as hloc rounds; size 0 keeps the points."""
    if size <= 0:
        return points
    return np.round(np.round((points + 0.5) / size) * size - 0.5, 2)


def _one_to_one(matches: np.ndarray, scores: np.ndarray) -> np.ndarray:
    """Indices of the matches kept when many-to-one matches are removed (hloc's
    ``get_unique_matches``): a match stays when it has the highest score among the matches
    of its keypoint in image 0 and among those of its keypoint in image 1 (ties: first)."""
    winners = []
    for side in (0, 1):
        order = np.lexsort((np.arange(len(matches)), -scores, matches[:, side]))  # by keypoint, best first
        first = np.ones(len(order), dtype=bool)
        first[1:] = matches[order[1:], side] != matches[order[:-1], side]
        winners.append(order[first])
    return np.sort(np.intersect1d(winners[0], winners[1]))


def merge_dense_matches(
    pairs: list[tuple[str, str]],
    raw_matches: list[tuple[np.ndarray, np.ndarray, np.ndarray]],
    max_keypoints: int | None = 8192,
    cell_size: float = 1.0,
    max_error: float = 1.0,
) -> tuple[dict[str, np.ndarray], list[tuple[np.ndarray, np.ndarray]]]:
    """Dense matches turned into per-image keypoints and per-pair matches as hloc's
    ``match_dense.match_and_assign`` does (conf ``loftr``: 1-px cells, max error 1 px,
    at most 8192 keypoints an image).

    ``raw_matches[i]`` = (points0 (N, 2), points1 (N, 2), scores (N,)) of ``pairs[i]`` in
    original pixels. Pairs are visited in hloc's order (by the fewer uses of their two
    images, then by name); each point falls into the ``max(cell_size, max_error)``-pixel
    cell of its image and adds its match score to its ``max_error``-pixel bin there. An
    image's keypoints are the best-scored bin of each cell, its ``max_keypoints``
    highest-summed ones first (hloc's argsort, reversed). Every raw match is then reassigned
    to the nearest kept keypoint within ``max_error`` on both sides (not always its own
    cell's), matches without one dropped, many-to-one removed (``_one_to_one``); scores
    are float16-rounded as hloc stores them.

    Returns (keypoints by image name, float32 (K, 2); per pair (matches (M, 2) int64 into
    those keypoints, ordered by image-0 keypoint, scores (M,) float32)).
    """
    from collections import Counter

    from scipy.spatial import KDTree

    if len(pairs) != len(raw_matches):
        raise ValueError(f"{len(pairs)} pairs but {len(raw_matches)} raw match sets; give one set a pair")
    uses = Counter(name for pair in pairs for name in pair)
    order = sorted(range(len(pairs)), key=lambda i: (min(uses[pairs[i][0]], uses[pairs[i][1]]), pairs[i]))
    cell_pixels = max(cell_size, max_error)
    cells: dict[str, dict[tuple[float, float], Counter]] = {}  # insertion order = first seen
    remaining = Counter(uses)
    keypoints: dict[str, np.ndarray] = {}
    for index in order:
        points0, points1, scores = raw_matches[index]
        for name, points in zip(pairs[index], (points0, points1)):
            image_cells = cells.setdefault(name, {})
            points = np.asarray(points, dtype=np.float32)
            # Scores summed in float32, as hloc's Counter sums its float32 scores.
            for cell, bin_, score in zip(map(tuple, _cell_centres(points, cell_pixels).tolist()),
                                         map(tuple, _cell_centres(points, int(max_error)).tolist()),
                                         np.asarray(scores, dtype=np.float32)):
                image_cells.setdefault(cell, Counter())[bin_] += score
        for name in pairs[index]:
            remaining[name] -= 1
            if remaining[name] > 0:
                continue
            best = [counter.most_common(1)[0] for counter in cells.pop(name).values()]
            points = np.array([position for position, _ in best], dtype=np.float32).reshape(-1, 2)
            summed = np.array([score for _, score in best], dtype=np.float32)
            if max_keypoints:
                kept = np.argsort(summed)[::-1][:max_keypoints]
                points = points[kept]
            keypoints[name] = points

    def nearest(points: np.ndarray, name: str) -> np.ndarray:
        targets = keypoints[name]
        if len(points) == 0 or len(targets) == 0:
            return np.full(len(points), -1, dtype=np.int64)
        distance, found = KDTree(targets).query(np.asarray(points, dtype=np.float32))
        return np.where(distance <= max_error, found, -1).astype(np.int64)

    merged = []
    for (name0, name1), (points0, points1, scores) in zip(pairs, raw_matches):
        ids0, ids1 = nearest(points0, name0), nearest(points1, name1)
        valid = (ids0 >= 0) & (ids1 >= 0)
        matches = np.stack([ids0[valid], ids1[valid]], axis=1).reshape(-1, 2)
        pair_scores = np.asarray(scores, dtype=np.float32)[valid]
        kept = _one_to_one(matches, pair_scores)
        matches, pair_scores = matches[kept], pair_scores[kept]
        by_keypoint0 = np.argsort(matches[:, 0], kind="stable")
        merged.append((matches[by_keypoint0], pair_scores[by_keypoint0].astype(np.float16).astype(np.float32)))
    return keypoints, merged


MATCHER_TYPES: dict[str, Callable[[dict[str, Any], torch.device], Callable[..., Matches]]] = {
    "nn": NearestNeighbourMatcher,
    "lightglue": LightGlueMatcher,
    "superglue": SuperGlueMatcher,
    "loftr": LoFTRMatcher,
}


def build_matcher(conf: dict[str, Any], device: torch.device) -> Callable[..., Matches]:
    if conf["type"] == "imm":  # vismatch is imported only by imm methods (opt-in environment)
        from .imm import ImmPairMatcher

        return ImmPairMatcher(conf, device)
    try:
        kind = MATCHER_TYPES[conf["type"]]
    except KeyError:
        raise KeyError(f"unknown matcher type {conf['type']!r}; known: {', '.join(MATCHER_TYPES)}") from None
    return kind(conf, device)
