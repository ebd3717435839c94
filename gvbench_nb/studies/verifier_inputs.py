"""What the verifier comparison reads from a run: cached matches, a place-disjoint split, per-verifier scores."""

from __future__ import annotations

import os
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pandas as pd

from gvbench_nb.data.sequences import Pair, Sequence, frame_index
from gvbench_nb.evaluation import run_tables
from gvbench_nb.io_utils import progress_bar
from gvbench_nb.protocol.ransac import filter_and_fit
from gvbench_nb.runner import image_features, input_checks, pair_matching, scoring
from gvbench_nb.verification.sue import sue as spatial_uncertainty

# ------------------------------------------------------------------ registry --
ESTIMATOR_SHORT_NAMES: dict[str, str] = {
    "FM_RANSAC": "ransac",
    "USAC_DEFAULT": "degensac",
    "USAC_ACCURATE": "lo-ransac",
    "USAC_MAGSAC": "magsac",
}
MODEL_SHORT_NAMES: dict[str, str] = {"fundamental": "F", "homography": "H"}
PAPER_VERIFIER = "gv-F-ransac-inliers"
# ------------------------------------------------------------------- split --
SPLIT_TRAIN, SPLIT_TEST, SPLIT_DROPPED = "train", "test", "dropped"


# A homography needs 4 matches, a fundamental matrix 8 (fewer: no model, score 0).
MIN_MATCHES = {"fundamental": 8, "homography": 4}


# Per-pair features of the learned combination (see ``gv_features``).
FEATURES = ("log_inliers", "log_matches", "inlier_ratio", "inliers_over_keypoints", "inlier_hull_area", "inlier_spread")


def place_disjoint_split(
    pairs: pd.DataFrame,
    train_fraction: float = 0.45,
    gap_frames: int = 20,
    tolerance: int = 2,
    position: Callable[[str], int] = frame_index,
) -> pd.Series:
    """'train' / 'test' / 'dropped' for each pair: train holds pairs with both frames in the first
    ``train_fraction`` of the frames, test those beyond a ``gap_frames`` gap (> 2 * ``tolerance``), so no
    place is in both. Gardens Point, defaults: train 0-89, test 110-199."""
    if gap_frames < 2 * tolerance:
        raise ValueError(
            f"gap_frames={gap_frames} < 2 * tolerance ({2 * tolerance}): a place of tolerance "
            f"{tolerance} frames could then reach both splits; widen the gap"
        )
    query_frames = pairs["query"].map(position).to_numpy()
    reference_frames = pairs["reference"].map(position).to_numpy()
    lo = int(min(query_frames.min(), reference_frames.min()))
    hi = int(max(query_frames.max(), reference_frames.max()))
    train_end = lo + int(np.floor(train_fraction * (hi - lo + 1))) - 1
    test_start = train_end + gap_frames + 1
    if train_end < lo or test_start > hi:
        raise ValueError(
            f"frames {lo}-{hi} leave no room for train (to {train_end}) and test (from {test_start}); "
            "lower gap_frames or change train_fraction"
        )
    in_train = (query_frames <= train_end) & (reference_frames <= train_end)
    in_test = (query_frames >= test_start) & (reference_frames >= test_start)
    split = np.where(in_train, SPLIT_TRAIN, np.where(in_test, SPLIT_TEST, SPLIT_DROPPED))
    return pd.Series(split, index=pairs.index, name="split")


def split_summary(pairs: pd.DataFrame, split: pd.Series, position: Callable[[str], int] = frame_index) -> pd.DataFrame:
    """Pairs, positives, queries and the frame range of each split (for the notebooks)."""
    rows = []
    for name in (SPLIT_TRAIN, SPLIT_TEST, SPLIT_DROPPED):
        part = pairs[split == name]
        frames = pd.concat([part["query"], part["reference"]]).map(position) if len(part) else pd.Series([], dtype=int)
        extent = f"{frames.min()}-{frames.max()}" if len(frames) else "-"
        rows.append((name, len(part), int(part["label"].sum()), part["query"].nunique(), extent))
    return pd.DataFrame(rows, columns=["split", "pairs", "positives", "queries", "frames"])


# ----------------------------------------------------------- cached matches --
@dataclass
class PairMatches:
    """One pair's cached matches in original pixels, row i of points0 matched to row i of points1."""

    points0: np.ndarray  # (M, 2)
    points1: np.ndarray  # (M, 2)
    match_scores: np.ndarray  # (M,)
    inlier_mask: np.ndarray  # (M,) the run's FM_RANSAC inliers
    num_keypoints0: int
    num_keypoints1: int
    image_size0: tuple[int, int]  # (width, height)
    image_size1: tuple[int, int]


class CachedMatches:
    """Read access to one finished run's matches (``<output_dir>/<method>``'s, in the cache folder its
    run.json names unless ``cache_dir`` is given): sparse methods index the feature cache's keypoints,
    dense ones store their points. A pair the cache lacks (deleted, or another machine's) is matched
    again from its images with the run's conf and seed, in one line saying so."""

    def __init__(
        self, output_dir: str | os.PathLike[str], method: str, cache_dir: str | os.PathLike[str] | None = None
    ) -> None:
        self.output_dir = Path(output_dir)
        self.method = method
        self.run = run_tables.load_run(self.output_dir, method)
        self.conf = self.run["conf"]
        self.seed = int(self.run["seed"])
        self.sequence = self.run["sequence"]
        self.image_root = Path(self.run["image_root"])
        self.pairs = scoring.load_pairs_table(self.output_dir, method)
        self.cache = run_tables.resolve_cache_dir(self.output_dir, cache_dir, method)
        self.matches = pair_matching.match_store(self.cache, self.conf, self._pair_list_keys())
        extractor = self.conf["extractor"]
        self.features = image_features.feature_store(self.cache, extractor) if extractor else None
        self._read_features = lru_cache(maxsize=512)(self._features_of)
        # An image (BGR, as ``cv2.imread``) is read once for the pairs that share it.
        self.image = lru_cache(maxsize=48)(self._image_of)

    def _run_sequence(self) -> Sequence:
        pairs = [
            Pair(q, r, int(lb)) for q, r, lb in zip(self.pairs["query"], self.pairs["reference"], self.pairs["label"])
        ]
        return Sequence(self.sequence, self.image_root, pairs)

    def _pair_list_keys(self) -> dict[Any, str] | None:
        """The pair keys of the run's pair list, for a dense method whose store is chosen by it; else None."""
        if pair_matching.dense_merge_options(self.conf["matcher"]) is None:
            return None
        return pair_matching.pair_keys(self._run_sequence(), self.seed)

    def match_missing(self, names: Iterable[tuple[str, str]]) -> None:
        """Match and verify again from their images, as the run did (its conf, seed and device), the pairs
        of ``names`` (query, reference) the cache lacks, into the cache, saying so in one line (a dense
        method that merges keypoints across pairs: the run's every pair)."""
        wanted = set(names)
        sequence = self._run_sequence()
        missing = [
            p
            for p in sequence.pairs
            if (p.query, p.reference) in wanted
            and pair_matching.pair_key(self.image_root, p.query, p.reference, self.seed) not in self.matches
        ]
        if not missing:
            return
        if self._pair_list_keys() is None:
            sequence = Sequence(self.sequence, self.image_root, missing)
        print(
            f"{self.label}: the cache {self.cache} lacks {len(missing)} pair(s) of this run, first "
            f"{missing[0].query} {missing[0].reference}; matching {len(sequence.pairs)} pair(s) again from the images"
        )
        device = str(self.run.get("device_request", "auto"))  # the run's, where this machine has it
        device = device if input_checks.device_problem(device) is None else "auto"
        if self.features is not None:
            image_features.extract_features(sequence, self.conf["extractor"], self.cache, device, progress=False)
            self.features.refresh()
        pair_matching.match_and_verify(sequence, self.conf, self.cache, device, self.seed, progress=False)
        self.matches.refresh()

    @property
    def label(self) -> str:
        """'<method> (<profile>) on <sequence>': what every number of these matches came from."""
        return f"{self.method} ({self.conf['profile']}) on {self.sequence}"

    def _features_of(self, name: str) -> tuple[np.ndarray, tuple[int, int]]:
        assert self.features is not None
        key = image_features.image_key(self.image_root, name)
        if key not in self.features:
            raise KeyError(
                f"features of {name!r} are not in {self.features.folder}; pass cache_dir= the run's "
                "cache folder (its params' cache_dir)"
            )
        entry = self.features.read(key)
        # float32: the cache may hold float16 (as hloc stores it), whose squares overflow in statistics.
        return (
            np.asarray(entry["keypoints"], dtype=np.float32),
            (int(entry["image_size"][0]), int(entry["image_size"][1])),
        )

    def _image_of(self, name: str) -> np.ndarray:
        path = self.image_root / name
        image = cv2.imread(str(path), cv2.IMREAD_COLOR)
        if image is None:
            raise FileNotFoundError(f"cannot read image {path} (run {self.output_dir / self.method})")
        return image

    def pair(self, query: str, reference: str) -> PairMatches:
        key = pair_matching.pair_key(self.image_root, query, reference, self.seed)
        if key not in self.matches:
            self.match_missing([(query, reference)])
        if key not in self.matches:
            raise KeyError(f"{query} {reference} is not a pair of the run {self.output_dir / self.method}")
        entry = self.matches.read(key)
        scores = np.asarray(entry["match_scores"], dtype=np.float64).reshape(-1)
        inlier_mask = np.asarray(entry["inlier_mask"], dtype=bool).reshape(-1)
        if "points0" in entry:  # dense matcher: its matched points are its keypoints
            p0, p1 = entry["points0"].reshape(-1, 2), entry["points1"].reshape(-1, 2)
            n0, n1 = len(p0), len(p1)
            size0, size1 = tuple(self.image(query).shape[1::-1]), tuple(self.image(reference).shape[1::-1])
        else:
            keypoints0, size0 = self._read_features(query)
            keypoints1, size1 = self._read_features(reference)
            index = np.asarray(entry["matches"], dtype=np.int64).reshape(-1, 2)
            p0, p1, n0, n1 = keypoints0[index[:, 0]], keypoints1[index[:, 1]], len(keypoints0), len(keypoints1)
        return PairMatches(p0, p1, scores, inlier_mask, n0, n1, size0, size1)

    def pair_seed(self, query: str, reference: str) -> int:
        """The RANSAC seed the run used for this pair."""
        return pair_matching.pair_seed(self.seed, query, reference)

    def close(self) -> None:
        self.matches.close()
        if self.features is not None:
            self.features.close()


def match_lines(
    output_dir: str | os.PathLike[str],
    method: str,
    query: str,
    reference: str,
    cache_dir: str | os.PathLike[str] | None = None,
) -> dict[str, np.ndarray]:
    """Matched points of one pair (original pixels) and its inlier mask, for drawing."""
    cached = CachedMatches(output_dir, method, cache_dir)
    try:
        pair = cached.pair(query, reference)
    finally:
        cached.close()
    return {"points0": pair.points0, "points1": pair.points1, "inlier_mask": pair.inlier_mask}


def fit_inliers(pair: PairMatches, conf: dict[str, Any], seed: int) -> tuple[np.ndarray, int]:
    """(inlier mask, matches that entered the fit) by the run's own ``filter_and_fit``, so FM_RANSAC with
    the run's seed gives the stored mask."""
    options = {key: conf[key] for key in ("threshold_px", "confidence", "max_iters", "min_matches", "min_match_score")}
    options.update(
        model=conf["model"], method=conf["estimator"], few_matches=conf.get("few_matches", "zero"), seed=seed
    )
    return filter_and_fit(pair.points0, pair.points1, pair.match_scores, **options)


def hull_area_fraction(points: np.ndarray, image_size: tuple[int, int]) -> float:
    """Area of the convex hull of ``points`` over the image area (0 for fewer than 3 points)."""
    if len(points) < 3:
        return 0.0
    hull = cv2.convexHull(np.asarray(points, dtype=np.float32).reshape(-1, 1, 2))
    return float(cv2.contourArea(hull)) / float(image_size[0] * image_size[1])


def gv_features(pair: PairMatches, inlier_mask: np.ndarray, num_fitted: int) -> dict[str, float]:
    """Per-pair GV numbers: counts, normalised scores, the smaller inlier convex-hull area (fraction of
    the image) and the smaller inlier spread (mean per-axis std over the image diagonal)."""
    n_inliers = int(inlier_mask.sum())
    inliers0, inliers1 = pair.points0[inlier_mask], pair.points1[inlier_mask]

    def spread(points: np.ndarray, size: tuple[int, int]) -> float:
        return float(points.std(axis=0).mean() / np.hypot(*size)) if len(points) >= 2 else 0.0

    return {
        "num_matches": float(num_fitted),
        "num_inliers": float(n_inliers),
        "inliers": float(n_inliers),
        "inlier_ratio": n_inliers / num_fitted if num_fitted else 0.0,
        "inliers_over_keypoints": n_inliers / max(min(pair.num_keypoints0, pair.num_keypoints1), 1),
        "log_inliers": float(np.log1p(n_inliers)),
        "log_matches": float(np.log1p(num_fitted)),
        "inlier_hull_area": min(
            hull_area_fraction(inliers0, pair.image_size0), hull_area_fraction(inliers1, pair.image_size1)
        ),
        "inlier_spread": min(spread(inliers0, pair.image_size0), spread(inliers1, pair.image_size1)),
    }


def _pair_names(pairs: pd.DataFrame, desc: str, progress: bool) -> Any:
    """(query, reference) of each pair, under a progress bar that goes when done."""
    names = zip(pairs["query"], pairs["reference"])
    return progress_bar(names, total=len(pairs), desc=desc, disable=not progress, unit="pair", leave=False)


def gv_feature_table(
    cached: CachedMatches, pairs: pd.DataFrame, conf: dict[str, Any], progress: bool = True
) -> pd.DataFrame:
    """``gv_features`` of every pair (query, reference order kept), fitting once a pair with its run seed."""
    rows = []
    desc = f"{MODEL_SHORT_NAMES[conf['model']]}-{ESTIMATOR_SHORT_NAMES[conf['estimator']]}"
    cached.match_missing(zip(pairs["query"], pairs["reference"]))
    for query, reference in _pair_names(pairs, desc, progress):
        pair = cached.pair(query, reference)
        mask, num_fitted = fit_inliers(pair, conf, cached.pair_seed(query, reference))
        rows.append({"query": query, "reference": reference, **gv_features(pair, mask, num_fitted)})
    return pd.DataFrame(rows, index=pairs.index)


# ----------------------------------------------------------------------- SUE --
def sue_pair_scores(
    table: pd.DataFrame, slope: float = 10.0, top_k: int = 10, position: Callable[[str], int] = frame_index
) -> pd.DataFrame:
    """SUE as a per-pair score: per query, SUE (``sue.sue``, ``slope``) of its ``top_k`` GV-ranked candidates
    with distances 1 - s/max(s) and frame positions; each pair scores ``score / (1 + sqrt(SUE))``.
    Returns ``query_sue`` and ``score`` aligned to ``table``."""
    query_sue = pd.Series(np.nan, index=table.index)
    for _, group in table.groupby("query", sort=False):
        ranked = group.assign(_name=group["reference"]).sort_values(["score", "_name"], ascending=[False, True])
        top = ranked.head(top_k)
        scores = top["score"].to_numpy(dtype=np.float64)
        best = scores.max()
        distances = 1.0 - scores / best if best > 0 else np.zeros_like(scores)
        positions = top["reference"].map(position).to_numpy(dtype=np.float64)
        query_sue[group.index] = float(spatial_uncertainty(distances[None], positions[None], slope)[0])
    score = table["score"].to_numpy(dtype=np.float64) / (1.0 + np.sqrt(query_sue.to_numpy()))
    return pd.DataFrame({"query_sue": query_sue, "score": score}, index=table.index)


# --------------------------------------------------------------- Doppelgangers --
def doppelgangers_inputs(cached: CachedMatches, pairs: pd.DataFrame, size: int, progress: bool = True) -> np.ndarray:
    """(N, 10, S, S) classifier inputs built from the cached matches (``build_input``, pipeline's way:
    the classifier selects its own "matches" with confidence > 0.8 and F-RANSAC in its frame)."""
    from gvbench_nb.verification.doppelgangers import build_input

    inputs = []
    cached.match_missing(zip(pairs["query"], pairs["reference"]))
    for query, reference in _pair_names(pairs, f"doppelgangers inputs {size}px", progress):
        pair = cached.pair(query, reference)
        inputs.append(
            build_input(
                cached.image(query), cached.image(reference), pair.points0, pair.points1, pair.match_scores, size
            )
        )
    return np.stack(inputs) if inputs else np.zeros((0, 10, size, size), np.float32)


def balanced_subset(labels: np.ndarray, max_pairs: int | None, seed: int) -> np.ndarray:
    """Indices of at most ``max_pairs`` pairs, half true half false where possible (seeded);
    all indices when ``max_pairs`` is None or not smaller than the set."""
    labels = np.asarray(labels).astype(int)
    if max_pairs is None or max_pairs >= len(labels):
        return np.arange(len(labels))
    rng = np.random.default_rng(seed)
    positives, negatives = np.flatnonzero(labels == 1), np.flatnonzero(labels == 0)
    n_negative = min(len(negatives), max_pairs // 2)
    n_positive = min(len(positives), max_pairs - n_negative)
    n_negative = min(len(negatives), max_pairs - n_positive)
    chosen = np.r_[rng.choice(positives, n_positive, replace=False), rng.choice(negatives, n_negative, replace=False)]
    return np.sort(chosen)
