import numpy as np
import pytest
from helpers import two_view_scene

from gvbench_nb.protocol import ransac, recipes
from gvbench_nb.protocol.ransac import ESTIMATORS, fundamental_inliers, verify_matches


@pytest.mark.parametrize("method", list(ESTIMATORS))
def test_estimators_recover_the_planted_inliers(method):
    p0, p1, truth = two_view_scene()
    mask = fundamental_inliers(p0, p1, method=method)
    assert (mask & truth).sum() >= 0.95 * truth.sum()
    assert (mask & ~truth).sum() <= 3  # a random match may fall near its epipolar line


def test_fewer_than_eight_matches_give_no_inliers():
    p0, p1, _ = two_view_scene(n_inliers=7, n_outliers=0)
    assert fundamental_inliers(p0, p1).sum() == 0


def test_same_seed_same_inliers():
    p0, p1, _ = two_view_scene(n_inliers=40, n_outliers=40, seed=3)
    assert (fundamental_inliers(p0, p1, seed=5) == fundamental_inliers(p0, p1, seed=5)).all()


def test_score_filter_drops_low_confidence_matches_before_ransac():
    p0, p1, truth = two_view_scene(n_inliers=100, n_outliers=0)
    matches = np.c_[np.arange(100), np.arange(100)]
    scores = np.where(np.arange(100) < 50, 0.9, 0.4)  # half below the 0.5 filter
    result = verify_matches(p0, p1, matches, scores, recipes.recipe("sift-nn", "paper")["verifier"])
    assert result["num_matches"] == 100 and result["num_matches_filtered"] == 50
    assert result["num_inliers"] >= 45 and not result["inlier_mask"][50:].any()


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
        mask = ransac.fundamental_inliers(
            points0, points1, threshold_px=1.0, method="USAC_DEFAULT", max_iters=10000, few_matches=rule
        )
        assert mask.sum() == expected
