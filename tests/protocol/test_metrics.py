import numpy as np
import pytest
from sklearn.metrics import average_precision_score

from gvbench_nb.protocol.metrics import (
    MetricsUndefinedError,
    average_precision,
    evaluate_scores,
    max_recall_at_full_precision,
    pr_curve,
)


def test_average_precision_equals_scikit_learn_on_random_scores():
    rng = np.random.default_rng(0)
    labels = rng.integers(0, 2, 500)
    scores = rng.integers(0, 60, 500) + 10 * labels  # integer scores: many ties, as inlier counts have
    assert average_precision(labels, scores) == pytest.approx(average_precision_score(labels, scores))


@pytest.mark.parametrize(
    ("labels", "scores", "expected"),
    [
        ([1, 1, 0, 1, 0], [50, 40, 30, 20, 10], 2 / 3),  # T T F T F: precision 1.0 down to recall 2/3
        ([0, 1, 1, 1], [99, 50, 40, 30], 0.0),  # a false pair scores highest
        ([1, 0, 1], [10, 10, 5], 0.0),  # the best true pair ties with a false one: precision 1/2 there
        ([1, 1, 0, 1], [10, 10, 5, 1], 2 / 3),  # a tie among true pairs only keeps precision 1
    ],
)
def test_max_recall_hand_computed_ties_counting_against_precision(labels, scores, expected):
    assert max_recall_at_full_precision(np.array(labels), np.array(scores)) == pytest.approx(expected)


def test_perfect_separation():
    result = evaluate_scores(np.array([1, 1, 0, 0]), np.array([9, 8, 2, 1]))
    assert result == {"n_pairs": 4, "n_positives": 2, "ap": 1.0, "max_recall": 1.0}


@pytest.mark.parametrize("labels", [[1, 1, 1], [0, 0, 0]])
def test_all_positive_or_all_negative_is_rejected(labels):
    with pytest.raises(MetricsUndefinedError, match="undefined"):
        evaluate_scores(np.array(labels), np.array([3, 2, 1]), where="x/pairs.csv")


def test_pr_curve_ends_at_precision_one_recall_zero_and_rejects_nan():
    curve = pr_curve(np.array([1, 0, 1]), np.array([3.0, 2.0, 1.0]))
    assert curve["precision"][-1] == 1.0 and curve["recall"][-1] == 0.0
    with pytest.raises(ValueError, match="NaN"):
        pr_curve(np.array([1, 0]), np.array([np.nan, 1.0]))


def released_evaluation(labels: np.ndarray, inliers: np.ndarray) -> tuple[float, float]:
    """GV-Bench@e10a93a eval.py:L246-251: AP and the PR curve of inliers / max(inliers);
    L21-24 max_recall: the largest recall where precision == 1.0."""
    from sklearn.metrics import precision_recall_curve

    normalised = inliers / max(inliers)
    precision, recall, _ = precision_recall_curve(labels, normalised)
    return float(average_precision_score(labels, normalised)), float(np.max(recall[np.where(precision == 1.0)]))


def test_metrics_equal_the_released_evaluation_without_its_division():
    rng = np.random.default_rng(4)
    labels = rng.integers(0, 2, 400)
    inliers = rng.integers(0, 40, 400) + 15 * labels * rng.integers(0, 2, 400)
    inliers[np.argmax(inliers)] += 100  # one large count: the division moves every score
    result = evaluate_scores(labels, inliers)
    ap, max_recall = released_evaluation(labels, inliers)
    assert result["ap"] == pytest.approx(ap, abs=1e-12) and result["max_recall"] == pytest.approx(max_recall)
    assert 0 < result["max_recall"] < 1
    # Every pair at 0 inliers: the released code divides 0 by 0; ours ranks the ties as one.
    zeros = np.zeros(400, int)
    with np.errstate(invalid="ignore"), pytest.raises(ValueError):
        released_evaluation(labels, zeros)
    assert evaluate_scores(labels, zeros)["ap"] == pytest.approx(labels.mean())


@pytest.mark.parametrize("seed", range(20))
def test_the_numpy_curve_and_ap_equal_scikit_learns_exactly(seed):
    """The package computes the curve with numpy; scikit-learn's, run here, is the reference."""
    from sklearn.metrics import precision_recall_curve

    rng = np.random.default_rng(seed)
    n = int(rng.integers(2, 300))
    labels = rng.integers(0, 2, n)
    labels[:2] = (0, 1)
    ties = seed % 2 == 0  # integer inlier counts tie often; normalised floats rarely
    scores = rng.integers(0, 1 + int(rng.integers(1, 40)), n) if ties else rng.random(n)
    precision, recall, thresholds = precision_recall_curve(labels, scores)
    ours = pr_curve(labels, scores)
    np.testing.assert_array_equal(ours["precision"], precision)
    np.testing.assert_array_equal(ours["recall"], recall)
    np.testing.assert_array_equal(ours["thresholds"], thresholds)
    assert average_precision(labels, scores) == average_precision_score(labels, scores)
    assert max_recall_at_full_precision(labels, scores) == float(recall[precision == 1.0].max())
