import numpy as np
import pytest
from helpers import two_view_scene

from gvbench_nb.protocol import ransac, recipes
from gvbench_nb.protocol.ransac import ESTIMATORS, fit_inliers, verify_matches


@pytest.mark.parametrize("method", list(ESTIMATORS))
def test_estimators_recover_the_planted_inliers(method):
    p0, p1, truth = two_view_scene()
    mask = fit_inliers(p0, p1, method=method)
    assert (mask & truth).sum() >= 0.95 * truth.sum()
    assert (mask & ~truth).sum() <= 3  # a random match may fall near its epipolar line
    p0, p1, _ = two_view_scene(n_inliers=40, n_outliers=40, seed=3)  # same seed, same inliers
    assert (fit_inliers(p0, p1, method=method, seed=5) == fit_inliers(p0, p1, method=method, seed=5)).all()


def test_resize_to_is_a_fixed_size_whatever_the_aspect_ratio():
    from gvbench_nb.protocol.images import target_size

    # The GV-Bench repository resizes every image to 512x288, portrait ones too.
    assert target_size(640, 480, None, resize_to=(512, 288)) == (512, 288)
    assert target_size(300, 900, 1600, resize_to=(512, 288)) == (512, 288)
    assert target_size(960, 540, 512) == (512, 288)


# Thirteen matches of a real sample pair (sift-nn, repository profile) where most query points
# match the same two reference points: OpenCV's USAC estimators raise on it instead of returning
# no model.
DEGENERATE_QUERY = [
    [304.17974853515625, 216.40762329101562], [366.32916259765625, 292.62890625],
    [369.8649597167969, 214.63534545898438], [394.4306640625, 348.8855285644531],
    [403.36676025390625, 344.5108642578125], [404.11065673828125, 367.6290588378906],
    [410.1116027832031, 378.9583435058594], [421.07855224609375, 397.42791748046875],
    [423.76470947265625, 376.2637634277344], [426.81683349609375, 378.54510498046875],
    [433.0713195800781, 400.0957946777344], [434.77215576171875, 242.8515625],
    [466.87860107421875, 247.93698120117188],
]  # fmt: skip
DEGENERATE_REFERENCE = [
    [302.02459716796875, 334.56494140625], [302.02459716796875, 334.56494140625],
    [302.02459716796875, 334.56494140625], [297.3966064453125, 317.9959716796875],
    [305.5838623046875, 328.83624267578125], [305.5838623046875, 328.83624267578125],
    [305.5838623046875, 328.83624267578125], [305.5838623046875, 328.83624267578125],
    [305.5838623046875, 328.83624267578125], [305.5838623046875, 328.83624267578125],
    [302.02459716796875, 334.56494140625], [451.85748291015625, 258.1497802734375],
    [84.86955261230469, 284.8394470214844],
]  # fmt: skip


def test_a_degenerate_pair_that_usac_raises_on_is_a_pair_without_a_model():
    import cv2

    points0, points1 = np.array(DEGENERATE_QUERY), np.array(DEGENERATE_REFERENCE)
    with pytest.raises(cv2.error):  # what OpenCV itself does with it
        cv2.setRNGSeed(0)
        cv2.findFundamentalMat(points0, points1, cv2.USAC_DEFAULT, 1.0, 0.99, 10000)
    for rule, expected in (("zero", 0), ("all", len(points0))):
        mask = ransac.fit_inliers(
            points0, points1, threshold_px=1.0, method="USAC_DEFAULT", max_iters=10000, few_matches=rule
        )
        assert mask.sum() == expected


# --------------------------------------------------- the references' own OpenCV calls --
def noisy_scene(n_inliers: int, n_outliers: int, seed: int, noise: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    points0, points1, _ = two_view_scene(n_inliers=n_inliers, n_outliers=n_outliers, seed=seed)
    return points0, points1 + np.random.default_rng(seed).normal(0, noise, points1.shape)


def reference_ransac(points0: np.ndarray, points1: np.ndarray, *args) -> np.ndarray:
    import cv2

    _, mask = cv2.findFundamentalMat(points0.astype(np.float64), points1.astype(np.float64), cv2.FM_RANSAC, *args)
    return mask.ravel().astype(bool)


def all_matches(n: int) -> np.ndarray:
    return np.repeat(np.arange(n)[:, None], 2, axis=1)


# Two scenes, each with the (threshold, confidence, iterations) that would give other inliers
# there: in the first RANSAC's confidence decides, in the second its iteration cap.
PAPER_SCENES = [(120, 80, 0, (3.0, 0.95, 1000)), (80, 80, 2, (3.0, 0.99, 2000))]


@pytest.mark.parametrize("n_inliers, n_outliers, seed, changed", PAPER_SCENES)
def test_paper_verifier_makes_the_released_evaluations_call(n_inliers, n_outliers, seed, changed):
    """GV-Bench@e10a93a eval.py:L134: cv2.findFundamentalMat(p0, p1, cv2.FM_RANSAC, 3.0), OpenCV's
    defaults otherwise, on the stored keypoints (original pixels)."""
    points0, points1 = noisy_scene(n_inliers, n_outliers, seed)
    expected = reference_ransac(points0, points1, 3.0)
    conf = recipes.recipe("sift-nn", "paper")["verifier"]
    sizes = (np.array([640, 480]), np.array([640, 480]))
    result = verify_matches(points0, points1, all_matches(len(points0)), np.ones(len(points0)), conf, image_sizes=sizes)
    np.testing.assert_array_equal(result["inlier_mask"], expected)
    # The case tells the settings apart.
    for other in (changed, (2.5, 0.99, 1000)):
        assert np.any(reference_ransac(points0, points1, *other) != expected), other


@pytest.mark.parametrize("seed", [2, 3])
def test_repository_verifier_fits_as_the_fork_does_on_512x288(seed):
    """The fork's base_matcher.py:L104 cv2.findFundamentalMat(FM_RANSAC, 3, 0.95, 2000) (GV-Bench
    main.py:L113-116) on the keypoints of the 512x288 images; our cache holds them in original
    pixels (here 1280x960), mapped there by the extraction's (k + 0.5) * scale - 0.5."""
    small0, small1 = noisy_scene(80, 80, seed)
    expected = reference_ransac(small0, small1, 3.0, 0.95, 2000)
    scale = np.array([1280 / 512, 960 / 288])
    original0, original1 = (small0 + 0.5) * scale - 0.5, (small1 + 0.5) * scale - 0.5
    conf = recipes.recipe("sift-nn", "repository")["verifier"]
    sizes = (np.array([1280, 960]), np.array([1280, 960]))
    result = verify_matches(
        original0, original1, all_matches(len(small0)), np.zeros(len(small0)), conf, image_sizes=sizes
    )
    np.testing.assert_array_equal(result["inlier_mask"], expected)
    for changed in [(3.0, 0.99, 2000), (3.0, 0.95, 1000), (2.5, 0.95, 2000)]:
        assert np.any(reference_ransac(small0, small1, *changed) != expected), changed


def test_score_filter_keeps_only_scores_above_one_half():
    """GV-Bench@e10a93a eval.py:L92 ``matches[scores > 0.5]``: a score of exactly 0.5 is dropped."""
    p0, p1, _ = two_view_scene(n_inliers=40, n_outliers=0)
    scores = np.where(np.arange(40) < 20, 0.5, np.nextafter(0.5, 1.0))
    result = verify_matches(p0, p1, all_matches(40), scores, recipes.recipe("disk-lg", "paper")["verifier"])
    assert result["num_matches"] == 40 and result["num_matches_filtered"] == 20
    assert result["num_inliers"] >= 18 and not result["inlier_mask"][:20].any()
