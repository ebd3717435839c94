"""Geometric verification: robust two-view model fit, score = inlier count."""

from __future__ import annotations

from collections.abc import Sequence as SequenceType
from typing import Any

import cv2
import numpy as np

from gvbench_nb.protocol import registry

# Robust estimators OpenCV offers for the fundamental matrix; FM_RANSAC is the paper's.
ESTIMATORS: dict[str, int] = {
    "FM_RANSAC": cv2.FM_RANSAC,
    "USAC_DEFAULT": cv2.USAC_DEFAULT,
    "USAC_MAGSAC": cv2.USAC_MAGSAC,
    "USAC_ACCURATE": cv2.USAC_ACCURATE,
}


FEW_MATCHES_RULES = ("zero", "all")
MODELS = ("fundamental", "homography")


def _fit(
    model: str,
    points0: np.ndarray,
    points1: np.ndarray,
    flag: int,
    threshold_px: float,
    confidence: float,
    max_iters: int,
) -> Any:
    if model == "fundamental":
        return cv2.findFundamentalMat(points0, points1, flag, threshold_px, confidence, max_iters)
    # FM_RANSAC names plain cv2.RANSAC for a homography
    flag = cv2.RANSAC if flag == cv2.FM_RANSAC else flag
    return cv2.findHomography(points0, points1, flag, threshold_px, maxIters=max_iters, confidence=confidence)


def fit_inliers(
    points0: np.ndarray,
    points1: np.ndarray,
    model: str = "fundamental",
    threshold_px: float = 3.0,
    confidence: float = 0.99,
    max_iters: int = 1000,
    method: str = "FM_RANSAC",
    min_matches: int = 8,
    seed: int = 0,
    few_matches: str = "zero",
) -> np.ndarray:
    """Inlier mask of a robust fundamental matrix (or homography) fit. Below ``min_matches`` or no
    model: ``few_matches`` "zero" (released evaluation code, May 2024 on) or "all" (the paper's
    period and the repository's code). OpenCV's fixed seed makes it depend only on the pair."""
    registry.check_choice("few_matches rule", few_matches, FEW_MATCHES_RULES, "the verifier conf")
    registry.lookup("verifier model", model, dict.fromkeys(MODELS))
    # The contiguous float64 (N, 2) arrays OpenCV's estimators take.
    points0 = np.ascontiguousarray(points0, dtype=np.float64).reshape(-1, 2)
    points1 = np.ascontiguousarray(points1, dtype=np.float64).reshape(-1, 2)
    if len(points0) != len(points1):
        raise ValueError(f"point arrays differ in length: {len(points0)} vs {len(points1)}")
    unverifiable = np.full(len(points0), few_matches == "all", dtype=bool)
    if len(points0) < max(min_matches, 8 if model == "fundamental" else 4):
        return unverifiable
    flag = registry.lookup("estimator", method, ESTIMATORS)
    cv2.setRNGSeed(int(seed))
    try:
        found, mask = _fit(model, points0, points1, flag, threshold_px, confidence, max_iters)
    except cv2.error:  # OpenCV's USAC raises where its RANSAC returns no model (degenerate matches)
        return unverifiable
    if found is None or mask is None or found.shape != (3, 3):
        return unverifiable
    return mask.ravel().astype(bool)


def to_verifier_frame(
    keypoints: np.ndarray, image_size: np.ndarray | SequenceType[int] | None, conf: dict[str, Any]
) -> np.ndarray:
    """Keypoints (original pixels) in the verifier's frame: "original", or "resize_to" mapped into
    the fixed (width, height) by (k + 0.5) * new / old - 0.5 (the repository fits F at 512x288)."""
    coordinates = conf.get("coordinates", "original")
    if coordinates == "original":
        return keypoints
    registry.check_choice("verifier coordinates", coordinates, ("original", "resize_to"))
    if image_size is None:
        raise ValueError(
            "the verifier conf fits in resized coordinates but no original image size was given; "
            "rerun extraction so the feature cache records each image's image_size"
        )
    scale = np.asarray(conf["resize_to"], dtype=np.float64) / np.asarray(image_size, dtype=np.float64)
    return (np.asarray(keypoints, dtype=np.float64) + 0.5) * scale - 0.5


def filter_and_fit(
    points0: np.ndarray,
    points1: np.ndarray,
    match_scores: np.ndarray,
    model: str = "fundamental",
    method: str = "FM_RANSAC",
    threshold_px: float = 3.0,
    confidence: float = 0.99,
    max_iters: int = 1000,
    min_matches: int = 8,
    min_match_score: float | None = None,
    few_matches: str = "zero",
    seed: int = 0,
) -> tuple[np.ndarray, int]:
    """The one verification step, used by the run and by every verifier after it: drop the
    matches scoring ``min_match_score`` or less (None keeps all), then fit ``model`` robustly.
    Returns (inlier mask over all the given matches, number of matches that entered the fit)."""
    keep = np.ones(len(points0), dtype=bool) if min_match_score is None else np.asarray(match_scores) > min_match_score
    inliers_of_kept = fit_inliers(
        np.asarray(points0)[keep],
        np.asarray(points1)[keep],
        model=model,
        threshold_px=threshold_px,
        confidence=confidence,
        max_iters=max_iters,
        method=method,
        min_matches=min_matches,
        seed=seed,
        few_matches=few_matches,
    )
    mask = np.zeros(len(keep), dtype=bool)
    mask[np.flatnonzero(keep)[inliers_of_kept]] = True
    return mask, int(keep.sum())


def verify_matches(
    keypoints0: np.ndarray,
    keypoints1: np.ndarray,
    matches: np.ndarray,
    match_scores: np.ndarray,
    conf: dict[str, Any],
    seed: int = 0,
    image_sizes: tuple[Any, Any] = (None, None),
) -> dict[str, Any]:
    """Score filter (``min_match_score``, None keeps all) then robust fit; returns counts and the
    inlier mask over ``matches``. ``image_sizes``: originals, for resized-frame verifiers."""
    points0 = to_verifier_frame(keypoints0[matches[:, 0]], image_sizes[0], conf)
    points1 = to_verifier_frame(keypoints1[matches[:, 1]], image_sizes[1], conf)
    inlier_mask, num_filtered = filter_and_fit(
        points0,
        points1,
        match_scores,
        model=conf["type"],
        method=conf["method"],
        threshold_px=conf["threshold_px"],
        confidence=conf["confidence"],
        max_iters=conf["max_iters"],
        min_matches=conf["min_matches"],
        min_match_score=conf.get("min_match_score", 0.0),
        few_matches=conf.get("few_matches", "zero"),
        seed=seed,
    )
    return {
        "num_matches": int(len(matches)),
        "num_matches_filtered": num_filtered,
        "num_inliers": int(inlier_mask.sum()),
        "inlier_mask": inlier_mask,
    }
