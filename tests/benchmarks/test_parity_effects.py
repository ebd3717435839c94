"""Each reference reading of the parity-effects benchmark changes the quantity it targets, on
constructed inputs, and leaves the package as it found it."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pandas as pd
import parity_effects
import pytest
import torch

from gvbench_nb import methods
from gvbench_nb.data.sequences import Pair, Sequence
from gvbench_nb.protocol import images, weights
from gvbench_nb.protocol.matching import build_matcher
from gvbench_nb.runner import image_features


def test_float16_scores_move_scores_just_above_the_filter_below_it():
    scores = np.array([0.50005, 0.5002, 0.6, 0.4, 0.49999], np.float32)
    threshold = methods.resolve_method("aliked-lg", "paper")["verifier"]["min_match_score"]
    ours, theirs = scores > threshold, parity_effects.float16_scores(scores) > threshold
    assert ours.tolist() == [True, True, True, False, False]
    assert theirs.tolist() == [False, False, True, False, False]


def test_descriptors_as_stored_skips_the_renormalisation_and_restores_it():
    matcher = build_matcher(methods.resolve_method("xfeat-nn", "paper")["matcher"], torch.device("cpu"))
    # Normalised, [0.9, 0.1] is the nearer direction to [1, 0]; as stored, [2, 1.9] has the larger product.
    features0 = {"descriptors": np.array([[1.0, 0.0]], np.float16)}
    features1 = {"descriptors": np.array([[2.0, 1.9], [0.9, 0.1]], np.float16)}
    ours, _ = matcher(features0, features1)
    normalize = torch.nn.functional.normalize
    with parity_effects.descriptors_as_stored():
        theirs, _ = matcher(features0, features1)
    assert torch.nn.functional.normalize is normalize
    assert ours.tolist() == [[0, 1]] and theirs.tolist() == [[0, 0]]


def lightglue_normalised(keypoints: np.ndarray, size: np.ndarray) -> np.ndarray:
    """LightGlue's keypoint normalisation (kornia's and cvg's): centred, by half the longest side."""
    size = np.asarray(size, np.float64)
    return (keypoints - size / 2) / (size.max() / 2)


@pytest.mark.parametrize("original, largest_gap", [((960, 540), 0.002), ((1280, 960), None)])
def test_input_frame_moves_what_lightglue_sees(original, largest_gap):
    keypoints = np.array([[0.0, 0.0], [100.5, 50.25], [original[0] - 1.0, original[1] - 1.0]], np.float32)
    features = {"keypoints": keypoints, "descriptors": np.zeros((3, 4), np.float32), "image_size": np.array(original)}
    framed = parity_effects.in_input_frame(features, (512, 288))
    assert framed["image_size"].tolist() == [512, 288]
    back = (framed["keypoints"].astype(np.float64) + 0.5) * np.array(original) / [512, 288] - 0.5
    np.testing.assert_allclose(back, keypoints, atol=1e-3)
    ours = lightglue_normalised(keypoints, features["image_size"])
    theirs = lightglue_normalised(framed["keypoints"], framed["image_size"])
    gap = np.abs(ours - theirs).max()
    assert gap > 1e-4
    if largest_gap is not None:  # 16:9 originals: only the pixel-centre offset
        assert gap < largest_gap
    else:  # 4:3 originals: the vertical positions are squeezed differently
        assert gap > 0.1
    assert features["keypoints"] is keypoints and features["image_size"].tolist() == list(original)


def test_float_images_keep_what_ours_rounds(tmp_path):
    rng = np.random.default_rng(0)
    path = tmp_path / "frame.png"
    cv2.imwrite(str(path), rng.integers(0, 256, (45, 80, 3), dtype=np.uint8))
    for method in ("xfeat-nn", "aliked-nn"):
        conf = methods.resolve_method(method, "repository")["extractor"]
        rounded, scale = images.load_for_extraction(path, conf)
        floating, float_scale = parity_effects.load_float_as_repository(path, conf)
        assert floating.shape == rounded.shape and floating.dtype == np.float32
        np.testing.assert_array_equal(scale, float_scale)
        difference = np.abs(floating - rounded)
        assert difference.max() <= 0.5 + 1e-3
        assert (difference > 0.01).mean() > 0.5
    loader = image_features.load_for_extraction
    with parity_effects.float_images():
        assert image_features.load_for_extraction is parity_effects.load_float_as_repository
    assert image_features.load_for_extraction is loader
    with pytest.raises(ValueError):
        parity_effects.load_float_as_repository(path, methods.resolve_method("xfeat-nn", "paper")["extractor"])


def test_query_subset_keeps_every_nth_query_with_all_its_pairs():
    pairs = [Pair(f"q{q}", f"r{r}", int(q == r)) for q in range(25) for r in range(3)]
    sequence = Sequence("toy", Path("."), pairs)
    subset = parity_effects.query_subset(sequence, 10)
    assert [p.query for p in subset.pairs] == ["q0"] * 3 + ["q10"] * 3 + ["q20"] * 3
    assert parity_effects.query_subset(sequence, 1) is sequence


def test_changes_count_matches_and_inliers_per_pair():
    table = pd.DataFrame({"num_inliers": [10, 0, 3]})
    positions = [np.array([[0, 1, 5, 5], [2, 3, 6, 6]]), np.zeros((0, 4)), np.array([[1, 1, 1, 1]])]
    ours = (table, [(p, np.ones(len(p), bool)) for p in positions])
    # The same raw matches; the score filter of the reading drops one of the first pair's.
    theirs = (table.assign(num_inliers=[8, 0, 3]), [(p, np.ones(len(p), bool)) for p in positions])
    theirs[1][0] = (positions[0], np.array([True, False]))
    theirs[1][2] = (np.array([[1, 1, 1, 2]]), np.array([True]))
    assert parity_effects.changes(ours, theirs) == {
        "raw_matches_changed": 2,
        "pairs_raw_matches_changed": 1,
        "matches_changed": 3,
        "pairs_matches_changed": 2,
        "inliers_changed": 2,
        "pairs_inliers_changed": 1,
    }


def test_rows_apply_to_the_methods_they_name():
    for row, spec in parity_effects.ROWS.items():
        for method in spec.methods:
            assert parity_effects.applies(row, methods.resolve_method(method, spec.profile)) is None, (row, method)
    assert parity_effects.applies("score-float16", methods.resolve_method("sift-nn", "paper"))
    assert parity_effects.applies("float-images", methods.resolve_method("orb-nn", "repository"))


def test_help_runs():
    with pytest.raises(SystemExit) as exit_info:
        parity_effects.main(["--help"])
    assert exit_info.value.code == 0


def test_cvg_lightglue_is_cvgs_and_matches():
    try:
        path = parity_effects.cvg_lightglue_file(None)
    except FileNotFoundError as error:
        pytest.skip(str(error))
    if not weights.is_present("lightglue_aliked"):
        pytest.skip("ALIKED LightGlue weights missing")
    conf = methods.resolve_method("aliked-lg", "paper")["matcher"]
    cvg = parity_effects.CvgLightGlue(conf, path)
    assert type(cvg.model).__module__ == "cvg_lightglue.lightglue"
    rng = np.random.default_rng(0)
    keypoints = rng.uniform(0, [960, 540], (64, 2)).astype(np.float32)
    descriptors = rng.normal(size=(64, 128)).astype(np.float32)
    descriptors /= np.linalg.norm(descriptors, axis=1, keepdims=True)
    side = {"keypoints": keypoints, "descriptors": descriptors, "image_size": np.array([960, 540])}
    matches, scores = cvg(side, side)
    assert len(matches) > 32 and (matches[:, 0] == matches[:, 1]).mean() > 0.9 and len(scores) == len(matches)
