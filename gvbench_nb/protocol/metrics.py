"""The paper's metrics: AP and max recall at 100% precision (MR), plus the PR curve."""

from __future__ import annotations

from typing import Any

import numpy as np

from gvbench_nb import GVBenchError

# The PR curve and AP follow scikit-learn's ``precision_recall_curve`` and
# ``average_precision_score`` step for step (tests/protocol/test_metrics.py holds them equal on ties
# and random scores); numpy alone, since importing scikit-learn costs a run more than evaluating.


class MetricsUndefinedError(GVBenchError, ValueError):
    """AP and MR are undefined: the pairs have no positives or no negatives."""


def check_defined(labels: Any, where: str) -> None:
    """Raise ``MetricsUndefinedError`` unless the 0/1 ``labels`` hold both a positive and a negative."""
    n_positive, count = int(np.sum(labels)), len(labels)
    if n_positive == 0 or n_positive == count:
        kind = "positives" if n_positive == 0 else "negatives"
        raise MetricsUndefinedError(
            f"{where}: {count} pairs with no {kind}: AP and MR are undefined; "
            "use pairs with both true and false loop closures (check the labels or --limit)"
        )


def _check(labels: np.ndarray, scores: np.ndarray, where: str) -> tuple[np.ndarray, np.ndarray]:
    labels = np.asarray(labels).astype(int).ravel()
    scores = np.asarray(scores, dtype=np.float64).ravel()
    if len(labels) != len(scores):
        raise ValueError(f"{where}: {len(labels)} labels but {len(scores)} scores")
    if not np.isin(labels, (0, 1)).all():
        raise ValueError(f"{where}: labels must be 0 or 1")
    check_defined(labels, where)
    if not np.isfinite(scores).all():
        raise ValueError(f"{where}: scores contain NaN or infinity")
    return labels, scores


def _curve(labels: np.ndarray, scores: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Precision and recall at each distinct score, highest first, then (1, 0), as scikit-learn's curve."""
    order = np.argsort(scores, kind="mergesort")[::-1]
    scores, labels = scores[order], labels[order]
    last = np.r_[np.flatnonzero(np.diff(scores)), len(scores) - 1]  # the last pair of each distinct score
    true_positives = np.cumsum(labels)[last].astype(np.float64)
    precision = true_positives / (last + 1)
    recall = true_positives / true_positives[-1]
    return np.r_[precision[::-1], 1.0], np.r_[recall[::-1], 0.0], scores[last][::-1]


def average_precision(labels: np.ndarray, scores: np.ndarray, where: str = "metrics") -> float:
    precision, recall, _ = _curve(*_check(labels, scores, where))
    return float(-np.sum(np.diff(recall) * precision[:-1]))


def max_recall_at_full_precision(labels: np.ndarray, scores: np.ndarray, where: str = "metrics") -> float:
    """Largest recall among PR-curve points with precision exactly 1.0; a false pair tied with
    the best true pair lowers precision there, so MR can be 0."""
    precision, recall, _ = _curve(*_check(labels, scores, where))
    return float(recall[precision == 1.0].max())


def pr_curve(labels: np.ndarray, scores: np.ndarray, where: str = "metrics") -> dict[str, np.ndarray]:
    precision, recall, thresholds = _curve(*_check(labels, scores, where))
    return {"precision": precision, "recall": recall, "thresholds": thresholds}


def evaluate_scores(labels: np.ndarray, scores: np.ndarray, where: str = "metrics") -> dict[str, Any]:
    labels, scores = _check(labels, scores, where)
    return {
        "n_pairs": int(len(labels)),
        "n_positives": int(labels.sum()),
        "ap": average_precision(labels, scores, where),
        "max_recall": max_recall_at_full_precision(labels, scores, where),
    }
