"""The bootstrap over queries: AP and MR of weighted resamples of a run's pairs, the resampling
unit being the query (every pair of a drawn query comes along).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd

from gvbench_nb.evaluation import run_tables


# ------------------------------------------------------------------ bootstrap --
def weighted_ap_max_recall(
    labels: np.ndarray, scores: np.ndarray, weights: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """AP and MR of many weightings of the same pairs at once.

    ``weights`` is (B, N): how often each pair counts in each of B resamples. Equals
    scikit-learn's ``average_precision_score`` and our ``max_recall_at_full_precision``
    on the repeated pairs (tied scores form one threshold, as there). NaN where a
    resample holds no true pair.
    """
    labels = np.asarray(labels).astype(bool)
    scores = np.asarray(scores, dtype=np.float64)
    weights = np.atleast_2d(np.asarray(weights, dtype=np.float64))
    order = np.argsort(-scores, kind="mergesort")
    sorted_scores = scores[order]
    # Last index of each run of equal scores: the curve's threshold points.
    ends = np.r_[np.nonzero(np.diff(sorted_scores))[0], len(scores) - 1]
    w = weights[:, order]
    positive = labels[order]
    true_positives = np.cumsum(w * positive, axis=1)[:, ends]
    false_positives = np.cumsum(w * ~positive, axis=1)[:, ends]
    total_positive = true_positives[:, -1]
    with np.errstate(invalid="ignore", divide="ignore"):
        predicted = true_positives + false_positives
        precision = np.where(predicted > 0, true_positives / np.where(predicted > 0, predicted, 1), 1.0)
        gained = np.diff(true_positives, axis=1, prepend=0.0)
        ap = (gained * precision).sum(axis=1) / total_positive
        reachable = np.where(false_positives == 0, true_positives, 0.0).max(axis=1)
        max_recall = reachable / total_positive
    invalid = total_positive <= 0
    ap[invalid] = np.nan
    max_recall[invalid] = np.nan
    return ap, max_recall


def query_resample_weights(query_codes: np.ndarray, n_resamples: int, seed: int) -> np.ndarray:
    """(B, N) pair weights: each resample draws the queries with replacement and every
    pair counts as often as its query was drawn (pairs of a query stay together)."""
    query_codes = np.asarray(query_codes)
    n_queries = int(query_codes.max()) + 1
    rng = np.random.default_rng(seed)
    drawn = rng.integers(0, n_queries, size=(n_resamples, n_queries))
    flat = drawn + n_queries * np.arange(n_resamples)[:, None]
    counts = np.bincount(flat.ravel(), minlength=n_resamples * n_queries).reshape(n_resamples, n_queries)
    return counts[:, query_codes]


@dataclass
class Bootstrap:
    """Resampled AP and MR of several methods on the same query resamples."""

    methods: list[str]
    estimates: pd.DataFrame  # index method, columns ap, max_recall (all queries)
    samples: dict[str, pd.DataFrame]  # metric -> (B rows, one column a method)
    n_queries: int
    n_pairs: int
    seed: int

    def intervals(self, level: float = 0.95) -> pd.DataFrame:
        """Percentile CIs: method, metric, estimate, low, high, n_valid (resamples with a true pair)."""
        tail = 100 * (1 - level) / 2
        rows = []
        for metric, frame in self.samples.items():
            for method in self.methods:
                values = frame[method].to_numpy()
                valid = values[~np.isnan(values)]
                low, high = np.percentile(valid, [tail, 100 - tail]) if len(valid) else (np.nan, np.nan)
                rows.append(
                    {
                        "method": method,
                        "metric": metric,
                        "estimate": self.estimates.loc[method, metric],
                        "low": low,
                        "high": high,
                        "n_valid": len(valid),
                    }
                )
        return pd.DataFrame(rows)

    def pairwise(self, metric: str = "max_recall", level: float = 0.975) -> pd.DataFrame:
        """Every ordered pair of methods: the share of resamples where A beats B, ties,
        and ``a_better`` = A beats B in more than ``level`` of them."""
        frame = self.samples[metric]
        rows = []
        for a in self.methods:
            for b in self.methods:
                if a == b:
                    continue
                both = frame[[a, b]].dropna()
                wins = float((both[a] > both[b]).mean()) if len(both) else float("nan")
                ties = float((both[a] == both[b]).mean()) if len(both) else float("nan")
                rows.append(
                    {
                        "metric": metric,
                        "method_a": a,
                        "method_b": b,
                        "a_beats_b": wins,
                        "tied": ties,
                        "a_better": bool(wins > level),
                    }
                )
        return pd.DataFrame(rows)

    def ranking_matrix(self, metric: str = "max_recall", level: float = 0.975) -> pd.DataFrame:
        """Square table: '>' where the row method is significantly better than the column's,
        '<' where worse, '~' where neither."""
        pairs = self.pairwise(metric, level)
        matrix = pd.DataFrame("", index=self.methods, columns=self.methods)
        for row in pairs.itertuples():
            reverse = pairs[(pairs.method_a == row.method_b) & (pairs.method_b == row.method_a)].iloc[0]
            matrix.loc[row.method_a, row.method_b] = ">" if row.a_better else ("<" if reverse.a_better else "~")
        return matrix


def bootstrap(tables: dict[str, pd.DataFrame], n_resamples: int = 1000, seed: int = 0) -> Bootstrap:
    """Resample QUERIES with replacement (seeded) and recompute every method's AP and MR.

    The same resamples serve every method (a paired bootstrap), so pairwise
    comparisons are fair. 1000 resamples of 2000 pairs take well under a second a method.
    """
    aligned = run_tables.align_tables(tables)
    query_codes = pd.factorize(aligned["query"])[0]
    weights = query_resample_weights(query_codes, n_resamples, seed)
    labels = aligned["label"].to_numpy()
    methods = list(tables)
    samples: dict[str, dict[str, np.ndarray]] = {"ap": {}, "max_recall": {}}
    estimates = {}
    for method in methods:
        scores = aligned[f"score:{method}"].to_numpy(dtype=float)
        samples["ap"][method], samples["max_recall"][method] = weighted_ap_max_recall(labels, scores, weights)
        ap, max_recall = weighted_ap_max_recall(labels, scores, np.ones((1, len(labels))))
        estimates[method] = {"ap": ap[0], "max_recall": max_recall[0]}
    return Bootstrap(
        methods=methods,
        estimates=pd.DataFrame(estimates).T,
        samples={metric: pd.DataFrame(values) for metric, values in samples.items()},
        n_queries=int(query_codes.max()) + 1,
        n_pairs=len(aligned),
        seed=seed,
    )
