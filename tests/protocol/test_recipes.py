"""The recipes' values against the reference code they reproduce, each copied from the reference
(file and line above it), not from our recipes. Read at: hloc fork gvbench 427cc99; GV-Bench main
11554cc; image-matching-models fork gvbench dd25ba4; cvg/LightGlue edb2b83; image-matching-toolbox
def5557. Library defaults (pycolmap, OpenCV, kornia) are asked of the installed library."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import torch

from gvbench_nb import methods
from gvbench_nb.protocol import features as extractors
from gvbench_nb.runner import pair_matching


def paper(name: str) -> dict:
    return methods.resolve_method(name, "paper")


def repository(name: str) -> dict:
    return methods.resolve_method(name, "repository")


def assert_holds(conf: dict, expected: dict, where: str) -> None:
    mismatched = {key: (conf.get(key), value) for key, value in expected.items() if conf.get(key) != value}
    assert not mismatched, f"{where}: (ours, reference) {mismatched}"


# ------------------------------------------------------------------ the paper profile --
# hloc/extract_features.py:L88-95 confs["sift"]: {"name": "dog"}, grayscale, resize_max 1600 (not
# forced); hloc/extractors/dog.py:L20-26 default_conf: first_octave 0, peak_threshold 0.01,
# descriptor "rootsift".
HLOC_SIFT = {"grayscale": True, "resize_max": 1600, "resize_force": False}
HLOC_DOG = {"first_octave": 0, "peak_threshold": 0.01, "root_sift": True}
# hloc/extract_features.py:L43-55 confs["superpoint_max"]: nms_radius 3, max_keypoints 4096,
# grayscale, resize_max 1600, resize_force True; hloc/extractors/superpoint.py:L29-34
# default_conf: keypoint_threshold 0.005, remove_borders 4.
HLOC_SUPERPOINT_MAX = {
    "grayscale": True,
    "resize_max": 1600,
    "resize_force": True,
    "nms_radius": 3,
    "max_keypoints": 4096,
    "keypoint_threshold": 0.005,
    "remove_borders": 4,
}
# hloc/extract_features.py:L104-114 confs["disk"]: max_keypoints 5000, RGB, resize_max 1600;
# hloc/extractors/disk.py:L7-13 default_conf: weights depth, nms_window_size 5, detection_threshold 0.
HLOC_DISK = {
    "grayscale": False,
    "resize_max": 1600,
    "resize_force": False,
    "max_keypoints": 5000,
    "weights": "depth",
    "nms_window": 5,
    "detection_threshold": 0.0,
}


def test_paper_extractors_are_hlocs_confs():
    assert_holds(paper("sift-nn")["extractor"], {**HLOC_SIFT, **HLOC_DOG, "type": "colmap_sift"}, "sift")
    for name in ("sp-nn", "sp-sg", "sp-lg"):
        assert_holds(paper(name)["extractor"], {**HLOC_SUPERPOINT_MAX, "type": "magicleap_superpoint"}, name)
    for name in ("disk-nn", "disk-lg"):
        assert_holds(paper(name)["extractor"], {**HLOC_DISK, "type": "kornia_disk"}, name)


def test_paper_sift_cap_is_pycolmaps_default():
    # hloc/extractors/dog.py:L26 max_keypoints -1: hloc sets no cap, so pycolmap's own
    # SiftExtractionOptions.max_num_features applies.
    import pycolmap

    assert paper("sift-nn")["extractor"]["max_keypoints"] == pycolmap.SiftExtractionOptions().max_num_features


def test_paper_matchers_are_hlocs_confs():
    # hloc/match_features.py:L38-45 confs["superglue"]: outdoor, sinkhorn_iterations 50;
    # hloc/matchers/superglue.py:L14 match_threshold 0.2.
    assert_holds(
        paper("sp-sg")["matcher"],
        {"type": "magicleap_superglue", "weights": "outdoor", "sinkhorn_iterations": 50, "match_threshold": 0.2},
        "sp-sg",
    )
    # hloc/match_features.py:L31-37 confs["disk+lightglue"]; hloc/matchers/lightglue.py:L7-11
    # depth_confidence 0.95, width_confidence 0.99; cvg/LightGlue lightglue/lightglue.py:L326
    # filter_threshold 0.1 (hloc leaves it at LightGlue's default).
    assert_holds(
        paper("disk-lg")["matcher"],
        {
            "type": "kornia_lightglue",
            "features": "disk",
            "depth_confidence": 0.95,
            "width_confidence": 0.99,
            "filter_threshold": 0.1,
        },
        "disk-lg",
    )
    # hloc/match_dense.py:L40-46 confs["loftr"]: outdoor, grayscale, resize_max 1024, dfactor 8,
    # max_error 1, cell_size 1; L547 max_kps 8192; hloc/matchers/loftr.py:L13 match_threshold 0.2.
    assert_holds(
        paper("loftr")["matcher"],
        {
            "type": "kornia_loftr",
            "weights": "outdoor",
            "grayscale": True,
            "resize_max": 1024,
            "resize_force": False,
            "multiple_of": 8,
            "coarse_threshold": 0.2,
            "merge_cell_size": 1,
            "merge_max_error": 1,
            "merge_max_keypoints": 8192,
        },
        "loftr",
    )


def test_paper_lightglue_model_runs_with_hlocs_confidences():
    # The recipe's LightGlue options reach the model (hloc/matchers/lightglue.py:L7-11).
    from gvbench_nb.protocol import weights
    from gvbench_nb.protocol.matching import build_matcher

    conf = paper("disk-lg")["matcher"]
    if not all(weights.is_present(c) for c in conf["checkpoints"]):
        pytest.skip("LightGlue's DISK weights are not in the torch hub cache")
    model = build_matcher(conf, torch.device("cpu")).model
    assert (model.conf.depth_confidence, model.conf.width_confidence, model.conf.filter_threshold) == (0.95, 0.99, 0.1)


def test_paper_verifier_is_the_released_evaluations():
    # GV-Bench@e10a93a eval.py:L92 keeps scores > 0.5; L126 fewer than 8 points -> no inliers;
    # L134 cv2.findFundamentalMat(FM_RANSAC, 3.0) (tests/protocol/test_verify.py runs the call
    # itself); keypoints read as stored, in original pixels (hloc/extract_features.py:L263).
    for name in methods.method_names():
        assert_holds(
            paper(name)["verifier"],
            {
                "type": "fundamental",
                "method": "FM_RANSAC",
                "threshold_px": 3.0,
                "min_match_score": 0.5,
                "min_matches": 8,
                "few_matches": "zero",
                "coordinates": "original",
            },
            name,
        )


# ------------------------------------------------------------- the repository profile --
# GV-Bench config/*.yaml:L6-7 image_width 512, image_height 288, for every matcher.
REPOSITORY_SIZE = [512, 288]
# The fork's matching/__init__.py:L71 get_matcher(max_num_keypoints=2048); main.py:L143 passes none.
REPOSITORY_KEYPOINTS = 2048


def test_repository_images_are_512x288_with_2048_keypoints():
    for name in methods.method_names():
        recipe = repository(name)
        image_conf = recipe["extractor"] or recipe["matcher"]
        assert image_conf["resize_to"] == REPOSITORY_SIZE, name
        assert image_conf["interpolation"] == "bilinear_antialias", name  # base_matcher.py:L49 Resize(antialias=True)
        assert image_conf.get("resize_max") is None, name
        if recipe["extractor"] is not None:  # features stored as float32
            assert recipe["extractor"]["max_keypoints"] == REPOSITORY_KEYPOINTS, name
            assert recipe["extractor"]["store_float16"] is False, name


def test_repository_lightglue_extractors_are_cvgs_defaults():
    # The fork's lightglue.py:L51, L58, L65 build cvg/LightGlue's extractors with
    # max_num_keypoints only. cvg/LightGlue@edb2b83: superpoint.py:L107-117 nms_radius 4,
    # detection_threshold 0.0005, remove_borders 4, resize 1024; disk.py:L8-20 depth,
    # nms_window_size 5, detection_threshold 0, resize 1024, RGB; aliked.py:L613-633
    # aliked-n16, detection_threshold 0.2, nms_radius 2, resize 1024.
    cvg = {
        "sp-lg": {"nms_radius": 4, "keypoint_threshold": 0.0005, "remove_borders": 4, "grayscale": True},
        "disk-lg": {"weights": "depth", "nms_window": 5, "detection_threshold": 0.0, "grayscale": False},
        "aliked-lg": {"model_name": "aliked-n16", "detection_threshold": 0.2, "nms_radius": 2},
    }
    for name, expected in cvg.items():
        assert_holds(repository(name)["extractor"], {**expected, "model_input_long_side": 1024}, name)


def test_repository_lightglue_is_the_forks():
    # The fork's lightglue.py:L52, L59, L66 LightGlue(features=..., depth_confidence=-1,
    # width_confidence=-1); filter_threshold left at cvg/LightGlue lightglue.py:L326's 0.1.
    for name, features in (("sp-lg", "superpoint"), ("disk-lg", "disk"), ("aliked-lg", "aliked")):
        assert_holds(
            repository(name)["matcher"],
            {"features": features, "depth_confidence": -1, "width_confidence": -1, "filter_threshold": 0.1},
            name,
        )


def test_repository_superglue_is_image_matching_toolboxs_sat_config():
    # The fork's matching_toolbox.py:L93-95 reads configs/superglue.yml's "sat" entry and sets
    # max_keypoints; image-matching-toolbox@def5557 configs/superglue.yml:L1-7, L12-15: outdoor,
    # sinkhorn_iterations 20, nms_radius 4, match_threshold 0.2; the keypoint threshold is
    # Magic Leap's SuperPoint default 0.005 (SuperGluePretrainedNetwork models/superpoint.py).
    recipe = repository("sp-sg")
    assert_holds(
        recipe["matcher"],
        {"type": "magicleap_superglue", "weights": "outdoor", "sinkhorn_iterations": 20, "match_threshold": 0.2},
        "sp-sg",
    )
    assert_holds(recipe["extractor"], {"nms_radius": 4, "keypoint_threshold": 0.005, "grayscale": True}, "sp-sg")
    assert "model_input_long_side" not in recipe["extractor"]  # the 512x288 grey image as it is


def test_repository_opencv_matchers_are_the_forks_ratio_test():
    # The fork's handcrafted.py:L43-49 knnMatch(k=2), kept when m.distance < 0.75 * n.distance
    # (lowe_thresh 0.75 at L69, L79), no mutual check; raw OpenCV descriptors (L38).
    for name in ("sift-nn", "orb-nn"):
        assert_holds(repository(name)["matcher"], {"rule": "knn_ratio", "ratio_threshold": 0.75, "mutual": False}, name)
    assert repository("sift-nn")["extractor"]["root_sift"] is False


def test_repository_xfeat_is_mutual_nearest_neighbour_without_a_threshold():
    # The fork's xfeat.py:L51 XFeat.match(..., min_cossim=-1): mutual nearest neighbours, every
    # similarity accepted; accelerated_features@515c4ce modules/xfeat.py:L23 detection_threshold 0.05.
    assert_holds(
        repository("xfeat-nn")["matcher"],
        {"type": "nn", "mutual": True, "ratio_threshold": None, "distance_threshold": None},
        "xfeat-nn",
    )
    assert repository("xfeat-nn")["extractor"]["detection_threshold"] == 0.05


def test_repository_loftr_is_kornias_outdoor_model_on_raw_pair_matches():
    # The fork's loftr.py:L10 kornia LoFTR(pretrained="outdoor") with kornia's own coarse
    # threshold, L13 tfm.Grayscale, L21 the raw matches of the pair: no merging across pairs.
    from kornia.feature.loftr.loftr import default_cfg

    matcher = repository("loftr")["matcher"]
    assert_holds(matcher, {"weights": "outdoor", "grayscale": True}, "loftr")
    assert matcher["coarse_threshold"] == default_cfg["match_coarse"]["thr"]
    assert pair_matching.dense_merge_options(matcher) is None


def test_repository_verifier_is_the_forks():
    # GV-Bench main.py:L113-116 ransac_kwargs 3 px, confidence 0.95, 2000 iterations (the fork's
    # base_matcher.py:L22-24 defaults are the same); base_matcher.py:L104 FM_RANSAC; L121 fewer
    # than 8 matches -> every match kept; no score filter; the fit on the 512x288 coordinates.
    for name in methods.method_names():
        assert_holds(
            repository(name)["verifier"],
            {
                "type": "fundamental",
                "method": "FM_RANSAC",
                "threshold_px": 3.0,
                "confidence": 0.95,
                "max_iters": 2000,
                "min_matches": 8,
                "few_matches": "all",
                "min_match_score": None,
                "coordinates": "resize_to",
                "resize_to": REPOSITORY_SIZE,
            },
            name,
        )


def _textured_512x288(seed: int = 0) -> np.ndarray:
    """A fine texture with blobs: both detectors find more than 2048 keypoints, so the cap binds."""
    rng = np.random.default_rng(seed)
    image = cv2.resize(rng.random((73, 129)).astype(np.float32), (512, 288), interpolation=cv2.INTER_CUBIC)
    for _ in range(60):
        centre = (int(rng.integers(0, 512)), int(rng.integers(0, 288)))
        cv2.circle(image, centre, int(rng.integers(2, 20)), float(rng.random()), -1)
    return np.clip(image * 255, 0, 255).astype(np.uint8)


@pytest.mark.parametrize(
    "name, reference",
    [
        # The fork's handcrafted.py:L72 cv2.SIFT_create(max_num_keypoints): OpenCV's defaults otherwise.
        ("sift-nn", lambda: cv2.SIFT_create(REPOSITORY_KEYPOINTS)),
        # The fork's handcrafted.py:L82 cv2.ORB_create(max_num_keypoints).
        ("orb-nn", lambda: cv2.ORB_create(REPOSITORY_KEYPOINTS)),
    ],
)
def test_repository_opencv_extractors_equal_the_forks_detectors(name, reference):
    image = _textured_512x288()
    ours = extractors.build_extractor(repository(name)["extractor"], torch.device("cpu"))(image.astype(np.float32))
    keypoints, descriptors = reference().detectAndCompute(image, None)
    assert len(keypoints) > 0.95 * REPOSITORY_KEYPOINTS  # the cap binds (ORB's levels share it unevenly)
    np.testing.assert_array_equal(ours["keypoints"], np.array([k.pt for k in keypoints], np.float32))
    np.testing.assert_array_equal(ours["descriptors"], descriptors.astype(ours["descriptors"].dtype))


@pytest.mark.parametrize("profile", ["paper", "repository"])
def test_disk_pads_its_input_to_a_multiple_of_16(profile):
    # hloc/extractors/disk.py:L12 and cvg/LightGlue disk.py:L14 pad_if_not_divisible True:
    # kornia's DISK refuses sizes that are not multiples of 16 unless told to pad.
    from kornia.feature import DISK

    from gvbench_nb.protocol import weights

    conf = methods.resolve_method("disk-nn", profile)["extractor"]
    if not weights.is_present("disk_depth"):
        pytest.skip("DISK's weights are not in the torch hub cache")
    extractor = extractors.build_extractor(conf, torch.device("cpu"))
    image = _textured_512x288()[:50, :70].astype(np.float32)[..., None].repeat(3, axis=2)
    with pytest.raises(ValueError, match="divisible by 16"):
        DISK.from_pretrained("depth")(torch.zeros(1, 3, 50, 70), n=10, pad_if_not_divisible=False)
    keypoints = extractor(image)["keypoints"]
    assert len(keypoints) > 0 and (keypoints < [70, 50]).all()


@pytest.mark.parametrize(
    ("profile", "implementation", "reference"),
    [
        ("paper", "type: colmap_sift", "extractors/dog.py:L20 COLMAP SIFT via pycolmap"),
        ("repository", "type: opencv_sift", "handcrafted.py:L68 SiftNNMatcher: OpenCV SIFT"),
    ],
)
def test_a_printed_recipe_names_its_implementation_and_its_reference_lines(capsys, profile, implementation, reference):
    from gvbench_nb import cli

    assert cli.main(["methods", "sift-nn", "--profile", profile]) == 0
    printed = capsys.readouterr().out
    assert implementation in printed and reference in printed
    # The verifier's reference, written once in the file's header, is printed with every recipe.
    assert "verifier (every recipe)" in printed
