"""LoFTR, a dense matcher, run and merged as hloc does (``match_dense.py``)."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np
import torch

from gvbench_nb.protocol import weights
from gvbench_nb.protocol.matching.base import Matcher


def loftr_call(
    model: Callable[[dict[str, torch.Tensor]], dict[str, torch.Tensor]],
    image0: torch.Tensor,
    image1: torch.Tensor,
    swap_images: bool = True,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """LoFTR on a pair -> (points0, points1, confidences). ``swap_images`` runs it as
    ``hloc/matchers/loftr.py`` does (image 1 first, so image 0 is the refined one); the GV-Bench
    fork (``matching/im_models/loftr.py``) passes the pair as it is."""
    if not swap_images:
        output = model({"image0": image0, "image1": image1})
        first, second = output["keypoints0"], output["keypoints1"]
    else:
        output = model({"image0": image1, "image1": image0})
        first, second = output["keypoints1"], output["keypoints0"]
    return (
        first.cpu().numpy().astype(np.float32),
        second.cpu().numpy().astype(np.float32),
        output["confidence"].cpu().numpy().astype(np.float32),
    )


class LoFTRMatcher(Matcher):
    """kornia LoFTR as a dense pair matcher on two prepared grayscale images (float32, 0..255):
    points in their pixels and confidences, merged across pairs by ``merge_dense_matches``."""

    type = "kornia_loftr"
    dense = True

    def __init__(self, conf: dict[str, Any], device: torch.device):
        from kornia.feature import LoFTR

        self.device = device
        self.swap_images = conf.get("swap_images", True)
        model = LoFTR(pretrained=None)
        model.coarse_matching.thr = conf.get("coarse_threshold", 0.2)

        def unwrap(checkpoint: dict[str, Any]) -> dict[str, Any]:
            return {k.removeprefix("matcher."): v for k, v in checkpoint.get("state_dict", checkpoint).items()}

        (checkpoint,) = conf["checkpoints"]
        self.model = weights.load_pretrained(model, checkpoint, device, unwrap)

    @torch.inference_mode()
    def __call__(self, image0: np.ndarray, image1: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        def tensor(image: np.ndarray) -> torch.Tensor:
            return torch.from_numpy(image).float().div(255.0)[None, None].to(self.device)

        return loftr_call(self.model, tensor(image0), tensor(image1), self.swap_images)


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
    """Dense matches of ``pairs`` (original pixels) to per-image keypoints and per-pair matches as
    hloc's ``match_dense.match_and_assign``: cell scores summed, ``max_keypoints`` best cells kept,
    matches reassigned within ``max_error``, many-to-one removed, scores float16-rounded."""
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
            for cell, bin_, score in zip(
                map(tuple, _cell_centres(points, cell_pixels).tolist()),
                map(tuple, _cell_centres(points, int(max_error)).tolist()),
                np.asarray(scores, dtype=np.float32),
            ):
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
