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


def test_max_recall_hand_computed():
    # Sorted by score: T T F T F -> precision 1.0 holds down to recall 2/3.
    labels = np.array([1, 1, 0, 1, 0])
    scores = np.array([50, 40, 30, 20, 10])
    assert max_recall_at_full_precision(labels, scores) == pytest.approx(2 / 3)


def test_max_recall_is_zero_when_a_false_pair_scores_highest():
    labels = np.array([0, 1, 1, 1])
    scores = np.array([99, 50, 40, 30])
    assert max_recall_at_full_precision(labels, scores) == 0.0


def test_max_recall_counts_ties_against_precision():
    # The best true pair ties with a false pair: at that threshold precision is 1/2, so MR = 0.
    labels = np.array([1, 0, 1])
    scores = np.array([10, 10, 5])
    assert max_recall_at_full_precision(labels, scores) == 0.0
    # A tie among true pairs only keeps precision 1.
    labels = np.array([1, 1, 0, 1])
    scores = np.array([10, 10, 5, 1])
    assert max_recall_at_full_precision(labels, scores) == pytest.approx(2 / 3)


def test_perfect_separation():
    labels = np.array([1, 1, 0, 0])
    scores = np.array([9, 8, 2, 1])
    result = evaluate_scores(labels, scores)
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
