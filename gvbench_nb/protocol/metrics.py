"""The paper's metrics: AP and max recall at 100% precision (MR), plus the PR curve."""

from __future__ import annotations

from typing import Any

import numpy as np

from gvbench_nb import GVBenchError

# scikit-learn is imported by the functions that use it: importing it takes longer than
# a small run's evaluation, and the modules that import this one do not all evaluate.


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


def average_precision(labels: np.ndarray, scores: np.ndarray, where: str = "metrics") -> float:
    from sklearn.metrics import average_precision_score

    labels, scores = _check(labels, scores, where)
    return float(average_precision_score(labels, scores))


def max_recall_at_full_precision(labels: np.ndarray, scores: np.ndarray, where: str = "metrics") -> float:
    """Largest recall among PR-curve points with precision exactly 1.0; a false pair tied with
    the best true pair lowers precision there, so MR can be 0."""
    from sklearn.metrics import precision_recall_curve

    labels, scores = _check(labels, scores, where)
    precision, recall, _ = precision_recall_curve(labels, scores)
    return float(recall[precision == 1.0].max())


def pr_curve(labels: np.ndarray, scores: np.ndarray, where: str = "metrics") -> dict[str, np.ndarray]:
    from sklearn.metrics import precision_recall_curve

    labels, scores = _check(labels, scores, where)
    precision, recall, thresholds = precision_recall_curve(labels, scores)
    return {"precision": precision, "recall": recall, "thresholds": thresholds}


def evaluate_scores(labels: np.ndarray, scores: np.ndarray, where: str = "metrics") -> dict[str, Any]:
    labels, scores = _check(labels, scores, where)
    return {
        "n_pairs": int(len(labels)),
        "n_positives": int(labels.sum()),
        "ap": average_precision(labels, scores, where),
        "max_recall": max_recall_at_full_precision(labels, scores, where),
    }
