"""AP and MR with bootstrap intervals over queries, and paired rankings of methods.

Both read the per-method pair tables of output folders and run ``bootstrap.bootstrap``:
queries are drawn with replacement (all pairs of a query together, since a query's pairs
share its image and are not independent) and every method is scored on the same draws,
so "A beats B" is counted resample by resample. The resampling unit is named in every
table these functions return.
"""

from __future__ import annotations

import os
from collections.abc import Sequence as SequenceType
from pathlib import Path

import pandas as pd

from gvbench_nb.evaluation import bootstrap, run_tables
from gvbench_nb.runner import method_outputs, scoring

RESAMPLING_UNIT = "query"
LEVEL = 0.95  # the intervals' coverage
DEFAULT_RESAMPLES = 1000
INTERVAL_COLUMNS = ("ap_low", "ap_high", "max_recall_low", "max_recall_high", "interval_unit")


def method_folders(output_dirs: SequenceType[str | os.PathLike[str]]) -> dict[str, Path]:
    """Which of ``output_dirs`` holds each method's finished results; a method in two is refused."""
    found: dict[str, Path] = {}
    for folder in map(Path, output_dirs):
        method_outputs.check_results_finished(folder)
        ran = scoring.methods_with_results(folder)
        if not ran:
            what = "does not exist" if not folder.exists() else "holds no method results (<method>/pairs.csv)"
            raise method_outputs.ResultsError(
                f"{folder} {what}; give the output folder of a finished run (python -m gvbench_nb run PARAMS)"
            )
        for method in ran:
            if method in found:
                raise run_tables.IncomparableRunsError(
                    f"method {method!r} has results in both {found[method]} and {folder}; "
                    "pass only one of the two folders"
                )
            found[method] = folder
    return found


def folder_tables(
    output_dirs: str | os.PathLike[str] | SequenceType[str | os.PathLike[str]], methods: SequenceType[str] | None = None
) -> dict[str, pd.DataFrame]:
    """The finished pair tables of ``methods`` (default: all) in one or more output folders,
    checked to be comparable (same pairs, same labels) before anything is resampled."""
    folders = [output_dirs] if isinstance(output_dirs, (str, os.PathLike)) else list(output_dirs)
    found = method_folders(folders)
    wanted = list(methods) if methods else list(found)
    absent = [m for m in wanted if m not in found]
    if absent:
        raise method_outputs.ResultsError(
            f"no results for method {absent[0]!r} in {', '.join(map(str, folders))}; run it on the same pairs first"
        )
    tables: dict[str, pd.DataFrame] = {}
    for folder in dict.fromkeys(found[m] for m in wanted):
        tables.update(run_tables.load_pairs_tables(folder, [m for m in wanted if found[m] == folder]))
    tables = {m: tables[m] for m in wanted}
    run_tables.align_tables(tables)
    return tables


def query_intervals(
    tables: dict[str, pd.DataFrame], n_resamples: int = DEFAULT_RESAMPLES, seed: int = 0, level: float = LEVEL
) -> pd.DataFrame:
    """One row a method: ``ap`` and ``max_recall`` on all pairs, each with its ``level``
    percentile interval over query resamples (``*_low``, ``*_high``), the unit resampled
    (``interval_unit``), ``n_queries``, ``n_pairs``, ``n_resamples``, ``seed``.

    Deterministic for a seed; the same draws serve every method.
    """
    return intervals_of(bootstrap.bootstrap(tables, n_resamples, seed), level)


def intervals_of(boot: bootstrap.Bootstrap, level: float = LEVEL) -> pd.DataFrame:
    """``query_intervals``' table from a bootstrap already drawn (so shares and intervals share its draws)."""
    long = boot.intervals(level).set_index(["method", "metric"])
    rows = []
    for method in boot.methods:
        row: dict[str, object] = {"method": method}
        for metric in run_tables.METRICS:
            row[metric] = float(long.loc[(method, metric), "estimate"])
            row[f"{metric}_low"] = float(long.loc[(method, metric), "low"])
            row[f"{metric}_high"] = float(long.loc[(method, metric), "high"])
        rows.append(row)
    table = pd.DataFrame(rows)
    table["interval_unit"] = RESAMPLING_UNIT
    table["n_queries"] = boot.n_queries
    table["n_pairs"] = boot.n_pairs
    table["n_resamples"] = len(boot.samples["ap"])
    table["seed"] = boot.seed
    return table


def interval_columns(
    tables: dict[str, pd.DataFrame], n_resamples: int = DEFAULT_RESAMPLES, seed: int = 0, level: float = LEVEL
) -> pd.DataFrame:
    """The interval columns for a results table, indexed by method: ``ap_low``, ``ap_high``,
    ``max_recall_low``, ``max_recall_high`` and ``interval_unit`` (what was resampled).

    Each method is resampled over its own queries, so a folder whose methods ran on
    different pairs (another ``--limit``) still gets its columns; methods of the same pairs
    in the same order get the same draws, hence the intervals ``query_intervals`` gives.
    """
    frames = [query_intervals({method: table}, n_resamples, seed, level) for method, table in tables.items()]
    if not frames:
        raise run_tables.IncomparableRunsError("no methods to give intervals: pass at least one pairs table")
    return pd.concat(frames, ignore_index=True).set_index("method")[list(INTERVAL_COLUMNS)]
