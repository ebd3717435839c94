"""The bootstrap over queries: AP and MR of weighted resamples of a run's pairs (a drawn query brings all its pairs),
their intervals, and paired rankings of methods."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd

from gvbench_nb.evaluation import run_tables

RANKED_SHARE = 0.95  # a ranking needs one method ahead in this share of the paired resamples
RESAMPLING_UNIT = "query"
LEVEL = 0.95  # the intervals' coverage
DEFAULT_RESAMPLES = 1000
INTERVAL_COLUMNS = ("ap_low", "ap_high", "max_recall_low", "max_recall_high", "interval_unit")
SHARE_COLUMNS = ["metric", "first", "second", "first_value", "second_value", "first_beats_second", "tied"]
SHARE_COLUMNS += ["second_beats_first", "verdict"]


# ------------------------------------------------------------------ bootstrap --
def weighted_ap_max_recall(
    labels: np.ndarray, scores: np.ndarray, weights: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """AP and MR of many weightings (``weights`` (B, N): each pair's count per resample) at once.
    Equals scikit-learn's ``average_precision_score`` and ``max_recall_at_full_precision`` on the repeated
    pairs; NaN where a resample holds no true pair."""
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

    def intervals(self, level: float = LEVEL) -> pd.DataFrame:
        """Percentile CIs: method, metric, estimate, low, high, n_valid (resamples with a true pair)."""
        tail = 100 * (1 - level) / 2
        rows = []
        for metric, frame in self.samples.items():
            for method in self.methods:
                valid = frame[method].dropna().to_numpy()
                low, high = np.percentile(valid, [tail, 100 - tail]) if len(valid) else (np.nan, np.nan)
                estimate = self.estimates.loc[method, metric]
                rows.append((method, metric, estimate, low, high, len(valid)))
        return pd.DataFrame(rows, columns=["method", "metric", "estimate", "low", "high", "n_valid"])

    def paired_shares(self, metric: str, ranked_share: float | None = None) -> pd.DataFrame:
        """Every pair of methods once (higher on all pairs first): shares of paired resamples won, tied
        and lost, and the verdict. A resample where both are equal counts for neither; a ranking needs
        ``ranked_share`` (default ``RANKED_SHARE``) strict wins in one direction, else a tie."""
        if metric not in run_tables.METRICS:
            raise ValueError(f"unknown metric {metric!r}: use one of {', '.join(run_tables.METRICS)}")
        share = RANKED_SHARE if ranked_share is None else ranked_share
        samples, estimates = self.samples[metric], self.estimates[metric]
        rows = []
        for i, a in enumerate(self.methods):
            for b in self.methods[i + 1 :]:
                first, second = (b, a) if estimates[b] > estimates[a] else (a, b)
                # Paired: one row of ``samples`` is one draw of queries for every method.
                both = samples[[first, second]].dropna()
                left, right = both[first].to_numpy(), both[second].to_numpy()
                wins, ties, losses = (
                    float(np.mean(op(left, right))) if len(both) else float("nan")
                    for op in (np.greater, np.equal, np.less)
                )
                verdict = (
                    f"{first} > {second}" if wins >= share else f"{second} > {first}" if losses >= share else "tie"
                )
                values = (float(estimates[first]), float(estimates[second]), wins, ties, losses, verdict)
                rows.append((metric, first, second, *values))
        return pd.DataFrame(rows, columns=SHARE_COLUMNS)

    def ranking_matrix(self, metric: str = "max_recall", ranked_share: float | None = None) -> pd.DataFrame:
        """Square table of ``paired_shares``' verdicts: '>' where the row method ranks above the
        column's, '<' where below, '~' for a tie."""
        matrix = pd.DataFrame("", index=self.methods, columns=self.methods)
        for row in self.paired_shares(metric, ranked_share).itertuples():
            above = row.verdict.split(" > ")[0] if row.verdict != "tie" else None
            for a, b in ((row.first, row.second), (row.second, row.first)):
                matrix.loc[a, b] = "~" if above is None else (">" if above == a else "<")
        return matrix


def bootstrap(tables: dict[str, pd.DataFrame], n_resamples: int = DEFAULT_RESAMPLES, seed: int = 0) -> Bootstrap:
    """Resample QUERIES with replacement (seeded) and recompute every method's AP and MR; the same
    resamples serve every method (a paired bootstrap)."""
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


def intervals_of(boot: Bootstrap, level: float = LEVEL) -> pd.DataFrame:
    """One row a method: ``ap``, ``max_recall``, their ``level`` percentile intervals (``*_low``, ``*_high``),
    ``interval_unit``, ``n_queries``, ``n_pairs``, ``n_resamples``, ``seed``; deterministic for a seed."""
    wide = boot.intervals(level).pivot(index="method", columns="metric", values=["estimate", "low", "high"])
    wide.columns = [metric if stat == "estimate" else f"{metric}_{stat}" for stat, metric in wide.columns]
    columns = [c for metric in run_tables.METRICS for c in (metric, f"{metric}_low", f"{metric}_high")]
    table = wide.loc[boot.methods, columns].astype(float).reset_index().rename_axis(columns=None)
    n_resamples = len(boot.samples["ap"])
    return table.assign(
        interval_unit=RESAMPLING_UNIT,
        n_queries=boot.n_queries,
        n_pairs=boot.n_pairs,
        n_resamples=n_resamples,
        seed=boot.seed,
    )


def interval_columns(
    tables: dict[str, pd.DataFrame], n_resamples: int = DEFAULT_RESAMPLES, seed: int = 0, level: float = LEVEL
) -> pd.DataFrame:
    """``ap_low``, ``ap_high``, ``max_recall_low``, ``max_recall_high``, ``interval_unit`` by method; each
    method is resampled over its own queries, so methods on different pairs still get columns."""
    frames = [intervals_of(bootstrap({method: table}, n_resamples, seed), level) for method, table in tables.items()]
    if not frames:
        raise run_tables.IncomparableRunsError("no methods to give intervals: pass at least one pairs table")
    return pd.concat(frames, ignore_index=True).set_index("method")[list(INTERVAL_COLUMNS)]
