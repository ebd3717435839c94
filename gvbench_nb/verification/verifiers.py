"""Verifiers beyond counting FM_RANSAC inliers, all scored from a run's CACHED matches.

A verifier turns a pair's matches into a score (higher = more likely the same place).
Each is a plain conf in ``VERIFIERS`` (like ``methods.METHODS``); its identity in
every table is ``verifier`` (the name) and ``conf_hash`` (``methods.conf_hash(conf)``).
Nothing here re-matches: the matches, their scores and the keypoints come from the
run's match store and the feature cache (``CachedMatches``).

Families
--------
``gv-<model>-<estimator>-<score>``
    Robust model fit on the cached matches (after the run's score filter).
    model: ``F`` fundamental (``cv2.findFundamentalMat``) or ``H`` homography
    (``cv2.findHomography``); estimator: ``ransac`` (FM_RANSAC / cv2.RANSAC, the
    paper's), ``degensac`` (USAC_DEFAULT), ``lo-ransac`` (USAC_ACCURATE: LO + graph
    cut), ``magsac`` (USAC_MAGSAC: MAGSAC++); score: ``inliers`` (the paper's),
    ``inlier_ratio`` (inliers / matches that entered the fit) or
    ``inliers_over_keypoints`` (inliers / the smaller keypoint count of the pair).
    ``gv-F-ransac-inliers`` with the run's seed reproduces the stored ``num_inliers``.
``sue``
    SUE (MODELS.md section 7) made into a per-pair score, see ``sue_pair_scores``.
``doppelgangers`` / ``doppelgangers-in-domain``
    P(same place) of the Doppelgangers classifier on the 10-channel input built
    from the cached matches: the official checkpoint (fails with
    ``MissingWeightsError`` when absent), or weights trained here on the train split.
``learned_combination`` / ``learned_combination+dg``
    Logistic regression over per-pair GV features (``FEATURES``), fitted on the
    train split; the ``+dg`` variant adds the in-domain classifier's probability.

Splits: learned verifiers must never see a test place while training, so
``place_disjoint_split`` cuts a frame-aligned sequence into disjoint frame ranges
with a gap wider than the ground-truth tolerance.
"""

from __future__ import annotations

import json
import os
import time
from collections.abc import Callable, Iterable
from collections.abc import Sequence as SequenceType
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pandas as pd
from tqdm import tqdm

from gvbench_nb import config, pipeline
from gvbench_nb import methods as method_registry
from gvbench_nb.data.sequences import frame_index
from gvbench_nb.evaluation import analysis
from gvbench_nb.io_utils import atomic_write_csv, atomic_write_json
from gvbench_nb.protocol import registry
from gvbench_nb.protocol.metrics import evaluate_scores
from gvbench_nb.protocol.ransac import ESTIMATORS, filter_and_fit, homography_inliers
from gvbench_nb.protocol.weights import MissingWeightsError
from gvbench_nb.verification.sue import sue as spatial_uncertainty

# ------------------------------------------------------------------ registry --
ESTIMATOR_SHORT_NAMES: dict[str, str] = {
    "FM_RANSAC": "ransac",
    "USAC_DEFAULT": "degensac",
    "USAC_ACCURATE": "lo-ransac",
    "USAC_MAGSAC": "magsac",
}
MODEL_SHORT_NAMES: dict[str, str] = {"fundamental": "F", "homography": "H"}
GV_SCORES = ("inliers", "inlier_ratio", "inliers_over_keypoints")
PAPER_VERIFIER = "gv-F-ransac-inliers"
# A homography needs 4 matches, a fundamental matrix 8 (fewer: no model, score 0).
MIN_MATCHES = {"fundamental": 8, "homography": 4}

# Per-pair features of the learned combination (see ``gv_features``).
FEATURES = ("log_inliers", "log_matches", "inlier_ratio", "inliers_over_keypoints", "inlier_hull_area", "inlier_spread")


def gv_conf(model: str, estimator: str, score: str) -> dict[str, Any]:
    """The conf of one GV verifier; thresholds are the paper's (3 px, 0.99, 1000 iterations)."""
    if model not in MODEL_SHORT_NAMES or estimator not in ESTIMATORS or score not in GV_SCORES:
        raise KeyError(
            f"unknown GV verifier ({model}, {estimator}, {score}); models {list(MODEL_SHORT_NAMES)}, "
            f"estimators {list(ESTIMATORS)}, scores {list(GV_SCORES)}"
        )
    return {
        "type": "gv",
        "model": model,
        "estimator": estimator,
        "score": score,
        "threshold_px": 3.0,
        "confidence": 0.99,
        "max_iters": 1000,
        "min_matches": MIN_MATCHES[model],
        "min_match_score": 0.5,
    }


def gv_name(model: str, estimator: str, score: str) -> str:
    return f"gv-{MODEL_SHORT_NAMES[model]}-{ESTIMATOR_SHORT_NAMES[estimator]}-{score}"


VERIFIERS: dict[str, dict[str, Any]] = {
    gv_name(m, e, s): gv_conf(m, e, s) for m in MODEL_SHORT_NAMES for e in ESTIMATORS for s in GV_SCORES
}
VERIFIERS.update(
    {
        # slope 10 on distances in [0, 1] (1 - score / best score): a candidate with 10% fewer
        # inliers than the best weighs e^-1 of it. The paper's 350 was for NetVLAD distances.
        "sue": {"type": "sue", "base": PAPER_VERIFIER, "slope": 10.0, "top_k": 10},
        "doppelgangers": {"type": "doppelgangers", "weights": "official", "size": 1024},
        "doppelgangers-in-domain": {
            "type": "doppelgangers",
            "weights": "in-domain",
            "size": 96,
            "epochs": 3,
            "batch_size": 8,
            "lr": 5e-4,
            "max_train_pairs": 300,
            "seed": 0,
        },
        "learned_combination": {
            "type": "learned_combination",
            "base": PAPER_VERIFIER,
            "features": list(FEATURES),
            "classifier": None,
            "C": 1.0,
        },
        "learned_combination+dg": {
            "type": "learned_combination",
            "base": PAPER_VERIFIER,
            "features": list(FEATURES),
            "classifier": "doppelgangers-in-domain",
            "C": 1.0,
        },
    }
)


def resolve_verifier(name: str, **overrides: Any) -> dict[str, Any]:
    """A verifier's conf (a copy) with ``overrides`` applied; unknown names list the valid ones."""
    if name not in VERIFIERS:
        raise registry.UnknownNameError(registry.unknown_name_message("verifier", name, VERIFIERS))
    conf = json.loads(json.dumps(VERIFIERS[name]))
    unknown = [k for k in overrides if k not in conf]
    if unknown:
        raise KeyError(f"verifier {name!r} has no option(s) {unknown}; its options: {sorted(conf)}")
    conf.update(overrides)
    return conf


# ------------------------------------------------------------------- split --
SPLIT_TRAIN, SPLIT_TEST, SPLIT_DROPPED = "train", "test", "dropped"


def place_disjoint_split(
    pairs: pd.DataFrame,
    train_fraction: float = 0.45,
    gap_frames: int = 20,
    tolerance: int = 2,
    position: Callable[[str], int] = frame_index,
) -> pd.Series:
    """'train' / 'test' / 'dropped' for each pair, so no place is in both splits.

    Frames span [lo, hi] (queries and references together, n = hi - lo + 1). Train
    holds the pairs whose query AND reference lie in [lo, lo + floor(train_fraction n) - 1],
    test those with both in [train_end + gap_frames + 1, hi]; any pair touching the
    gap or the other range is dropped. Frames i (train) and j (test) then differ by
    more than ``gap_frames`` >= 2 * ``tolerance``, so the places i +- tolerance and
    j +- tolerance never overlap. Gardens Point (frames 0-199), defaults: train
    0-89, test 110-199.
    """
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
        rows.append(
            {
                "split": name,
                "pairs": len(part),
                "positives": int(part["label"].sum()),
                "queries": part["query"].nunique(),
                "frames": f"{frames.min()}-{frames.max()}" if len(frames) else "-",
            }
        )
    return pd.DataFrame(rows)


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
    """Read access to one finished run's matches (``<output_dir>/<method>``), never re-matching.

    Sparse methods: matched keypoints from the feature cache (``cache_dir``, default
    ``<output_dir>/../cache``) indexed by the stored ``matches``; dense methods: the
    stored ``points0/points1`` (keypoints = matches there, as in ``pairs.csv``).
    """

    def __init__(
        self, output_dir: str | os.PathLike[str], method: str, cache_dir: str | os.PathLike[str] | None = None
    ) -> None:
        self.output_dir = Path(output_dir)
        self.method = method
        self.run = analysis.load_run(self.output_dir, method)
        self.conf = self.run["conf"]
        self.seed = int(self.run["seed"])
        self.sequence = self.run["sequence"]
        self.image_root = Path(self.run["image_root"])
        self.pairs = pipeline.load_pairs_table(self.output_dir, method)
        self.matches = pipeline.match_store(self.output_dir, self.conf)
        self.features = (
            pipeline.feature_store(analysis.resolve_cache_dir(self.output_dir, cache_dir), self.conf["extractor"])
            if self.conf["extractor"]
            else None
        )
        self._read_features = lru_cache(maxsize=512)(self._features_of)
        self._read_image = lru_cache(maxsize=48)(self._image_of)

    @property
    def label(self) -> str:
        """'<method> (<profile>) on <sequence>': what every number of these matches came from."""
        return f"{self.method} ({self.conf['profile']}) on {self.sequence}"

    def _features_of(self, name: str) -> tuple[np.ndarray, tuple[int, int]]:
        assert self.features is not None
        key = pipeline.image_key(self.image_root, name)
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

    def image(self, name: str) -> np.ndarray:
        """The BGR image (as ``cv2.imread``), cached for the pairs that share it."""
        return self._read_image(name)

    def pair(self, query: str, reference: str) -> PairMatches:
        key = pipeline.pair_key(self.image_root, query, reference, self.seed)
        if key not in self.matches:
            raise KeyError(
                f"pair {query} {reference} is not in the match store {self.matches.folder}; "
                f"rerun {self.method!r} on these pairs"
            )
        entry = self.matches.read(key)
        scores = np.asarray(entry["match_scores"], dtype=np.float64).reshape(-1)
        inlier_mask = np.asarray(entry["inlier_mask"], dtype=bool).reshape(-1)
        if "points0" in entry:  # dense matcher: its matched points are its keypoints
            p0, p1 = entry["points0"].reshape(-1, 2), entry["points1"].reshape(-1, 2)
            size0 = self.image(query).shape[1::-1]
            size1 = self.image(reference).shape[1::-1]
            return PairMatches(p0, p1, scores, inlier_mask, len(p0), len(p1), tuple(size0), tuple(size1))
        keypoints0, size0 = self._read_features(query)
        keypoints1, size1 = self._read_features(reference)
        index = np.asarray(entry["matches"], dtype=np.int64).reshape(-1, 2)
        return PairMatches(
            keypoints0[index[:, 0]],
            keypoints1[index[:, 1]],
            scores,
            inlier_mask,
            len(keypoints0),
            len(keypoints1),
            size0,
            size1,
        )

    def pair_seed(self, query: str, reference: str) -> int:
        """The RANSAC seed the run used for this pair."""
        return pipeline.pair_seed(self.seed, query, reference)

    def close(self) -> None:
        self.matches.close()
        if self.features is not None:
            self.features.close()


# ----------------------------------------------------------------- GV scores --


def fit_inliers(pair: PairMatches, conf: dict[str, Any], seed: int) -> tuple[np.ndarray, int]:
    """(inlier mask over all the pair's matches, number of matches that entered the fit).

    ``ransac.filter_and_fit``, the run's own step, so FM_RANSAC with the run's seed gives the
    stored mask.
    """
    return filter_and_fit(
        pair.points0,
        pair.points1,
        pair.match_scores,
        model=conf["model"],
        method=conf["estimator"],
        threshold_px=conf["threshold_px"],
        confidence=conf["confidence"],
        max_iters=conf["max_iters"],
        min_matches=conf["min_matches"],
        min_match_score=conf["min_match_score"],
        few_matches=conf.get("few_matches", "zero"),
        seed=seed,
    )


def hull_area_fraction(points: np.ndarray, image_size: tuple[int, int]) -> float:
    """Area of the convex hull of ``points`` over the image area (0 for fewer than 3 points)."""
    if len(points) < 3:
        return 0.0
    hull = cv2.convexHull(np.asarray(points, dtype=np.float32).reshape(-1, 1, 2))
    return float(cv2.contourArea(hull)) / float(image_size[0] * image_size[1])


def gv_features(pair: PairMatches, inlier_mask: np.ndarray, num_fitted: int) -> dict[str, float]:
    """Per-pair GV numbers: counts, both normalised scores and where the inliers lie.

    ``inlier_hull_area``: the smaller of the two images' inlier convex-hull areas, as
    a fraction of the image; ``inlier_spread``: the smaller of the two images' mean
    per-axis std of the inlier coordinates, over the image diagonal.
    """
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


def gv_feature_table(
    cached: CachedMatches, pairs: pd.DataFrame, conf: dict[str, Any], progress: bool = True
) -> pd.DataFrame:
    """``gv_features`` of every pair (query, reference order kept), fitting once a pair with its run seed."""
    rows = []
    desc = f"{MODEL_SHORT_NAMES[conf['model']]}-{ESTIMATOR_SHORT_NAMES[conf['estimator']]}"
    for query, reference in tqdm(
        zip(pairs["query"], pairs["reference"]),
        total=len(pairs),
        desc=desc,
        disable=not progress,
        unit="pair",
        leave=False,
    ):
        pair = cached.pair(query, reference)
        mask, num_fitted = fit_inliers(pair, conf, cached.pair_seed(query, reference))
        rows.append({"query": query, "reference": reference, **gv_features(pair, mask, num_fitted)})
    return pd.DataFrame(rows, index=pairs.index)


# ----------------------------------------------------------------------- SUE --
def sue_pair_scores(
    table: pd.DataFrame, slope: float = 10.0, top_k: int = 10, position: Callable[[str], int] = frame_index
) -> pd.DataFrame:
    """SUE of each query's GV-ranked candidates, turned into a per-pair score.

    ``table`` has query, reference and ``score`` (the base GV score, >= 0). For each query:
    1. rank its candidates by score (the "retrieval" ranking; ties by reference name)
       and keep the top ``top_k``;
    2. distances d_i = 1 - s_i / max_j s_j (0 for the best; all 0 when no candidate
       has a score, so the weights are uniform), positions p_i = frame index;
    3. query SUE = the weighted positional variance (``sue.sue`` with ``slope``), in frames^2;
    4. every pair of the query scores  score / (1 + sqrt(SUE)): its GV score
       discounted by the positional std of where the query's GV evidence points.
    A query whose strong candidates agree on one place keeps its scores; one whose
    evidence is split between distant places is discounted. Returns a frame with
    ``query_sue`` and ``score`` aligned to ``table``'s index.
    """
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
    for query, reference in tqdm(
        zip(pairs["query"], pairs["reference"]),
        total=len(pairs),
        desc=f"doppelgangers inputs {size}px",
        disable=not progress,
        unit="pair",
        leave=False,
    ):
        pair = cached.pair(query, reference)
        inputs.append(
            build_input(
                cached.image(query), cached.image(reference), pair.points0, pair.points1, pair.match_scores, None, size
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


def in_domain_weights_path(
    folder: str | os.PathLike[str], cached: CachedMatches, conf: dict[str, Any], split_conf: dict[str, Any]
) -> Path:
    """Where in-domain weights live; the name says what they are (sequence, matches, split,
    size, epochs, seed) and ends in the hash of everything that made them."""
    identity = {
        "verifier": conf,
        "split": split_conf,
        "matches": {
            "method": cached.method,
            "conf_hash": method_registry.conf_hash(cached.conf),
            "sequence": cached.sequence,
        },
    }
    name = (
        f"doppelgangers_in-domain_{cached.sequence}_{cached.method}-{cached.conf['profile']}_train-split"
        f"_size{conf['size']}_ep{conf['epochs']}_seed{conf['seed']}_{method_registry.conf_hash(identity)}.pt"
    )
    return Path(folder) / name


def train_in_domain(
    cached: CachedMatches, train_pairs: pd.DataFrame, conf: dict[str, Any], path: Path, progress: bool = True
) -> dict[str, Any]:
    """Train the Doppelgangers architecture on ``train_pairs`` (published recipe: focal loss, Adam)
    and save ``{'dec': state_dict, 'info': ...}`` at ``path`` (loadable by ``load_doppelgangers``).
    Returns the info: pairs used, seconds to build inputs and to train, the history."""
    import torch  # here only: reading cached matches and scoring them need no torch

    from gvbench_nb.verification.doppelgangers import (
        DoppelgangersClassifier,
        train_classifier,
    )

    chosen = balanced_subset(train_pairs["label"].to_numpy(), conf["max_train_pairs"], conf["seed"])
    subset = train_pairs.iloc[chosen]
    start = time.perf_counter()
    inputs = doppelgangers_inputs(cached, subset, conf["size"], progress)
    input_seconds = time.perf_counter() - start
    torch.manual_seed(conf["seed"])  # the initialisation; train_classifier seeds the batch order
    model = DoppelgangersClassifier()
    start = time.perf_counter()
    labels = np.array(subset["label"], dtype=np.int64)  # a writable copy (torch refuses read-only arrays)
    history = train_classifier(
        model,
        inputs,
        labels,
        epochs=conf["epochs"],
        lr=conf["lr"],
        batch_size=conf["batch_size"],
        seed=conf["seed"],
        progress=progress,
    )
    train_seconds = time.perf_counter() - start
    info = {
        "weights": path.name,
        "matches": cached.label,
        "conf": conf,
        "n_train_pairs": int(len(subset)),
        "n_train_positives": int(subset["label"].sum()),
        "input_seconds": input_seconds,
        "train_seconds": train_seconds,
        "torch_threads": torch.get_num_threads(),
        "history": history,
    }
    path.parent.mkdir(parents=True, exist_ok=True)
    torch.save({"dec": model.state_dict(), "info": info}, path)
    atomic_write_json(path.with_suffix(".json"), info)
    return info


# --------------------------------------------------------------- evaluation --
@dataclass
class VerifierBench:
    """Scores verifiers on one run's cached matches, with a place-disjoint split.

    ``pairs`` is the run's pairs table with a ``split`` column. Fits and inputs are
    computed once and reused by every verifier that needs them. ``overrides`` maps a
    verifier name to options replacing its registry conf (e.g. a smaller training);
    the changed conf is what ``conf_hash`` and ``conf`` record.
    """

    cached: CachedMatches
    pairs: pd.DataFrame
    split_conf: dict[str, Any]
    output_dir: Path
    progress: bool = True
    overrides: dict[str, dict[str, Any]] = field(default_factory=dict)
    weights_info: dict[str, dict[str, Any]] = field(default_factory=dict)  # verifier -> which weights scored it
    _gv: dict[str, pd.DataFrame] = field(default_factory=dict)
    _classifier: dict[str, pd.Series] = field(default_factory=dict)

    def conf(self, name: str) -> dict[str, Any]:
        """The verifier's registry conf with this bench's overrides."""
        return resolve_verifier(name, **self.overrides.get(name, {}))

    def used(self) -> pd.DataFrame:
        """Pairs of the train and test splits (dropped pairs are never scored)."""
        return self.pairs[self.pairs["split"] != SPLIT_DROPPED]

    def gv(self, conf: dict[str, Any]) -> pd.DataFrame:
        """GV features of every used pair under ``conf``'s model fit (computed once a fit conf)."""
        fit_conf = {k: v for k, v in conf.items() if k != "score"}
        key = method_registry.conf_hash(fit_conf)
        if key not in self._gv:
            self._gv[key] = gv_feature_table(self.cached, self.used(), fit_conf, self.progress)
        return self._gv[key]

    def classifier_probability(self, name: str, conf: dict[str, Any]) -> pd.Series:
        """P(same place) of a Doppelgangers verifier on every used pair."""
        if name in self._classifier:
            return self._classifier[name]
        from gvbench_nb.verification.doppelgangers import load_doppelgangers, predict

        if conf["weights"] == "official":
            model = load_doppelgangers()  # MissingWeightsError names the file and where to get it
            path = self.output_dir / f"doppelgangers_official_size{conf['size']}.pt"  # names the cached predictions
            self.weights_info[name] = {"weights": "official doppelgangers_classifier_loftr.pt"}
        else:
            path = in_domain_weights_path(self.output_dir, self.cached, conf, self.split_conf)
            if path.is_file() and path.with_suffix(".json").is_file():
                info = json.loads(path.with_suffix(".json").read_text())
                info["reused"] = True
            else:
                info = train_in_domain(
                    self.cached, self.pairs[self.pairs["split"] == SPLIT_TRAIN], conf, path, self.progress
                )
                info["reused"] = False
            model = load_doppelgangers(path)
            self.weights_info[name] = info
        used = self.used()
        # Predictions are cached beside the weights, keyed by pair: inference costs minutes on a CPU.
        cache = path.with_name(path.stem + f".predictions-{self.cached.method}-{self.cached.conf['profile']}.csv")
        if cache.is_file():
            known = pd.read_csv(cache, keep_default_na=False).set_index(["query", "reference"])["probability"]
            wanted = pd.MultiIndex.from_arrays([used["query"], used["reference"]])
            if wanted.isin(known.index).all():
                self.weights_info[name]["predictions"] = f"reused {cache.name}"
                self._classifier[name] = pd.Series(known.loc[wanted].to_numpy(), index=used.index)
                return self._classifier[name]
        start = time.perf_counter()
        inputs = doppelgangers_inputs(self.cached, used, conf["size"], self.progress)
        probability = predict(model, inputs)
        self.weights_info[name]["predict_seconds"] = time.perf_counter() - start
        atomic_write_csv(cache, used[["query", "reference"]].assign(probability=probability))
        self._classifier[name] = pd.Series(probability, index=used.index)
        return self._classifier[name]

    def scores(self, name: str, conf: dict[str, Any] | None = None) -> pd.Series:
        """The verifier's score of every used pair (index of ``pairs``)."""
        conf = conf or self.conf(name)
        kind = conf["type"]
        if kind == "gv":
            return self.gv(conf)[conf["score"]]
        if kind == "sue":
            base = self.used()[["query", "reference"]].assign(score=self.scores(conf["base"]))
            return sue_pair_scores(base, conf["slope"], conf["top_k"])["score"]
        if kind == "doppelgangers":
            return self.classifier_probability(name, conf)
        if kind == "learned_combination":
            features = self.combination_features(conf)
            model = fit_combination(
                features[self.used()["split"] == SPLIT_TRAIN],
                self.used().loc[self.used()["split"] == SPLIT_TRAIN, "label"],
                conf,
            )
            return pd.Series(model.predict_proba(features.to_numpy())[:, 1], index=features.index)
        raise KeyError(f"verifier {name!r} has unknown type {kind!r}")

    def combination_features(self, conf: dict[str, Any]) -> pd.DataFrame:
        features = self.gv(self.conf(conf["base"]))[list(conf["features"])].copy()
        if conf["classifier"]:
            features["classifier_probability"] = self.classifier_probability(
                conf["classifier"], self.conf(conf["classifier"])
            )
        return features

    def evaluate(
        self,
        names: Iterable[str],
        split: str = SPLIT_TEST,
        n_resamples: int = 1000,
        seed: int = 0,
    ) -> tuple[pd.DataFrame, dict[str, pd.DataFrame], analysis.Bootstrap | None]:
        """AP, MR and their query-bootstrap 95% CIs of each verifier on ``split``.

        A verifier that cannot run (missing weights) gets a row with its reason in
        ``status`` and no numbers. Returns (rows, per-verifier score tables, bootstrap).
        """
        rows, tables = [], {}
        part = self.used()[self.used()["split"] == split]
        for name in names:
            conf = self.conf(name)
            row = {
                "verifier": name,
                "conf_hash": method_registry.conf_hash(conf),
                "split": split,
                "matches": self.cached.label,
                "n_pairs": len(part),
                "n_positives": int(part["label"].sum()),
            }
            try:
                start = time.perf_counter()
                score = self.scores(name, conf)
                row["seconds"] = time.perf_counter() - start
            except MissingWeightsError as error:
                rows.append(
                    {
                        **row,
                        "status": f"unavailable: {str(error).splitlines()[0]}",
                        "conf": json.dumps(conf, sort_keys=True),
                    }
                )
                continue
            tables[name] = part[["query", "reference", "label"]].assign(score=score.loc[part.index].to_numpy())
            metrics = evaluate_scores(
                tables[name]["label"].to_numpy(),
                tables[name]["score"].to_numpy(),
                where=f"verifier {name} on the {split} split of {self.cached.label}",
            )
            weights = self.weights_info.get(name) or self.weights_info.get(conf.get("classifier") or "")
            rows.append(
                {
                    **row,
                    "ap": metrics["ap"],
                    "max_recall": metrics["max_recall"],
                    "status": "ok",
                    "weights": weights["weights"] if weights else "",
                    "conf": json.dumps(conf, sort_keys=True),
                }
            )
        results = pd.DataFrame(rows)
        boot = None
        if tables:
            boot = analysis.bootstrap(tables, n_resamples=n_resamples, seed=seed)
            wide = boot.intervals().pivot(index="method", columns="metric", values=["low", "high"])
            for metric in analysis.METRICS:
                results[f"{metric}_ci_low"] = results["verifier"].map(wide[("low", metric)])
                results[f"{metric}_ci_high"] = results["verifier"].map(wide[("high", metric)])
        columns = [
            "verifier",
            "split",
            "ap",
            "max_recall",
            "ap_ci_low",
            "ap_ci_high",
            "max_recall_ci_low",
            "max_recall_ci_high",
            "n_pairs",
            "n_positives",
            "matches",
            "weights",
            "seconds",
            "status",
            "conf_hash",
            "conf",
        ]
        return results.reindex(columns=columns), tables, boot


def fit_combination(features: pd.DataFrame, labels: pd.Series, conf: dict[str, Any]) -> Any:
    """Standardised features -> ``LogisticRegression`` (lbfgs, deterministic), fitted on the given pairs."""
    from sklearn.linear_model import LogisticRegression
    from sklearn.pipeline import make_pipeline
    from sklearn.preprocessing import StandardScaler

    labels = np.asarray(labels).astype(int)
    if len(np.unique(labels)) < 2:
        raise ValueError(
            f"the learned combination needs true and false training pairs; got {len(labels)} pairs "
            f"all labelled {labels[:1]}: widen the train split"
        )
    model = make_pipeline(StandardScaler(), LogisticRegression(C=conf["C"], max_iter=1000))
    return model.fit(features.to_numpy(dtype=np.float64), labels)


# ------------------------------------------------------------- entry points --
def ensure_method_results(params_file: str | os.PathLike[str], method: str, **overrides: Any) -> Path:
    """Run ``method`` with the params file (``overrides`` to ``config.load_params``) only when its
    ``pairs.csv`` is missing; never re-evaluates, so another run's folder is left as it is."""
    params = config.load_params(params_file, **overrides)
    output_dir = Path(params["output_dir"])
    if not (pipeline.method_dir(output_dir, method) / "pairs.csv").is_file():
        sequence = config.prepare_sequence(params)
        pipeline.run_method_of_params(params, sequence, method)
    return output_dir


def open_bench(
    results_dir: str | os.PathLike[str],
    method: str,
    output_dir: str | os.PathLike[str],
    cache_dir: str | os.PathLike[str] | None = None,
    progress: bool = True,
    overrides: dict[str, dict[str, Any]] | None = None,
    **split_options: Any,
) -> VerifierBench:
    """A ``VerifierBench`` on ``results_dir/method``'s cached matches, split with
    ``place_disjoint_split(**split_options)``; learned weights go to ``output_dir``."""
    cached = CachedMatches(results_dir, method, cache_dir)
    pairs = cached.pairs.copy()
    pairs["split"] = place_disjoint_split(pairs, **split_options)
    output_dir = Path(output_dir)
    output_dir.mkdir(parents=True, exist_ok=True)
    return VerifierBench(cached, pairs, dict(split_options), output_dir, progress, dict(overrides or {}))


def write_results(results: pd.DataFrame, output_dir: str | os.PathLike[str], name: str = "verifiers.csv") -> Path:
    """Merge ``results`` into ``<output_dir>/verifiers.csv`` (rows of the same verifier, split and
    matches are replaced; others kept, so both notebooks add to one table)."""
    path = Path(output_dir) / name
    keys = ["verifier", "split", "matches"]
    if path.is_file():
        old = pd.read_csv(path, keep_default_na=False)
        fresh = set(map(tuple, results[keys].astype(str).to_numpy()))
        old = old[[tuple(r) not in fresh for r in old[keys].astype(str).to_numpy()]]
        results = pd.concat([old, results], ignore_index=True)
    atomic_write_csv(path, results)
    return path


def verifier_table(results: pd.DataFrame) -> pd.DataFrame:
    """AP and MR with their 95% CIs as text (%), one row a verifier, for people."""

    def cell(row: pd.Series, metric: str) -> str:
        if row.get("status") != "ok":
            return "-"
        return f"{100 * row[metric]:.1f} [{100 * row[f'{metric}_ci_low']:.1f}, {100 * row[f'{metric}_ci_high']:.1f}]"

    return pd.DataFrame(
        {
            "verifier": results["verifier"],
            "AP % [95% CI]": [cell(r, "ap") for _, r in results.iterrows()],
            "MR % [95% CI]": [cell(r, "max_recall") for _, r in results.iterrows()],
            "status": results["status"],
            "weights": results["weights"].fillna(""),
        }
    ).set_index("verifier")


def best_by(
    results: pd.DataFrame, boot: analysis.Bootstrap, metric: str = "max_recall", baseline: str = PAPER_VERIFIER
) -> dict[str, Any]:
    """The verifier with the highest ``metric`` and its gain over ``baseline`` with a paired
    bootstrap 95% CI of the difference (same query resamples for both)."""
    ok = results[results["status"] == "ok"]
    winner = ok.loc[ok[metric].idxmax(), "verifier"]
    difference = (boot.samples[metric][winner] - boot.samples[metric][baseline]).dropna()
    low, high = np.percentile(difference, [2.5, 97.5]) if len(difference) else (np.nan, np.nan)
    estimate = float(ok.set_index("verifier").loc[winner, metric] - ok.set_index("verifier").loc[baseline, metric])
    return {
        "metric": metric,
        "winner": winner,
        "baseline": baseline,
        "difference": estimate,
        "difference_ci_low": float(low),
        "difference_ci_high": float(high),
        "winner_beats_baseline_share": float((difference > 0).mean()) if len(difference) else float("nan"),
    }


# ------------------------------------------------------- paper comparison --
PAPER_ROWS = {"SIFT+NN": "GV: SIFT+NN, F-RANSAC inliers", "Doppelgangers": "Doppelgangers"}


def doppelgangers_comparison(
    results: pd.DataFrame,
    paper: pd.DataFrame,
    sequence: str,
    verifiers_shown: SequenceType[str] = (PAPER_VERIFIER, "doppelgangers", "doppelgangers-in-domain"),
) -> pd.DataFrame:
    """GV vs Doppelgangers as the paper's supplementary table: ours on ``sequence``'s test split
    (source 'ours', with CIs and the weights used) beside the paper's SIFT+NN and Doppelgangers
    rows on its own sequences (source 'paper', as published). AP and MR as fractions."""
    ours = results[results["verifier"].isin(verifiers_shown)].copy()
    ours = ours.assign(source=analysis.OURS_LABEL, sequence=f"{sequence} (test split)")
    theirs = paper[paper["paper_name"].isin(list(PAPER_ROWS))].copy()
    theirs = theirs.assign(
        source=analysis.PAPER_LABEL, verifier=theirs["paper_name"].map(PAPER_ROWS), weights="", status="published"
    )
    columns = [
        "source",
        "sequence",
        "verifier",
        "ap",
        "max_recall",
        "ap_ci_low",
        "ap_ci_high",
        "max_recall_ci_low",
        "max_recall_ci_high",
        "status",
        "weights",
    ]
    return pd.concat([ours.reindex(columns=columns), theirs.reindex(columns=columns)], ignore_index=True)


__all__ = [
    "CachedMatches",
    "FEATURES",
    "GV_SCORES",
    "PAPER_ROWS",
    "PAPER_VERIFIER",
    "PairMatches",
    "VERIFIERS",
    "VerifierBench",
    "balanced_subset",
    "best_by",
    "doppelgangers_comparison",
    "ensure_method_results",
    "fit_combination",
    "fit_inliers",
    "gv_conf",
    "gv_feature_table",
    "gv_features",
    "gv_name",
    "homography_inliers",
    "in_domain_weights_path",
    "open_bench",
    "place_disjoint_split",
    "resolve_verifier",
    "split_summary",
    "sue_pair_scores",
    "train_in_domain",
    "verifier_table",
    "write_results",
]
