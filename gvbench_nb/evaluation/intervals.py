"""AP and MR with bootstrap intervals over queries (a query's pairs go together), and paired rankings of methods."""

from __future__ import annotations

import pandas as pd

from gvbench_nb.evaluation import bootstrap, run_tables

RESAMPLING_UNIT = "query"
LEVEL = 0.95  # the intervals' coverage
DEFAULT_RESAMPLES = 1000
INTERVAL_COLUMNS = ("ap_low", "ap_high", "max_recall_low", "max_recall_high", "interval_unit")


def query_intervals(
    tables: dict[str, pd.DataFrame], n_resamples: int = DEFAULT_RESAMPLES, seed: int = 0, level: float = LEVEL
) -> pd.DataFrame:
    """One row a method: ``ap``, ``max_recall``, their ``level`` percentile intervals (``*_low``, ``*_high``),
    ``interval_unit``, ``n_queries``, ``n_pairs``, ``n_resamples``, ``seed``; deterministic for a seed."""
    return intervals_of(bootstrap.bootstrap(tables, n_resamples, seed), level)


def intervals_of(boot: bootstrap.Bootstrap, level: float = LEVEL) -> pd.DataFrame:
    """``query_intervals``' table from a bootstrap already drawn (so shares and intervals share its draws)."""
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
    frames = [query_intervals({method: table}, n_resamples, seed, level) for method, table in tables.items()]
    if not frames:
        raise run_tables.IncomparableRunsError("no methods to give intervals: pass at least one pairs table")
    return pd.concat(frames, ignore_index=True).set_index("method")[list(INTERVAL_COLUMNS)]
