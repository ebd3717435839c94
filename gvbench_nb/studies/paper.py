"""What notebooks/analysis_paper.ipynb computes and draws, laid out as the paper: Table II (sequence
summary beside the paper's text), Table III (AP, MR, Average, ranks marked), Fig. 1 (published MR
radar) and Fig. 8 (one method's MR and AP across sequences)."""

from __future__ import annotations

import os
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import matplotlib.pyplot as plt
import numpy as np
import pandas as pd

from gvbench_nb.evaluation import plots, reference_values, run_tables
from gvbench_nb.studies import results_table

COUNTED = "counted from the list"
RUN_COUNTED = "counted from the run"
PAPER_TEXT = "paper (text)"
COUNTS = ["queries", "candidates", "pairs", "positives"]  # candidates: a query's
SUMMARY_COLUMNS = ["sequence", "source", "traverse", "condition", "viewpoint", *COUNTS]
AVERAGE = "Average"
PLACE_STYLES = {1: "font-weight: bold;", 2: "text-decoration: underline;", 3: "font-style: italic;"}


def _folder(path: str) -> str:
    return path.rsplit("/", 1)[0] if "/" in path else "."


def count_pairs(sequence: str, table: pd.DataFrame, source: str) -> dict[str, Any]:
    """One summary row of a (query, reference, label) table; traverse: query folder vs reference folders."""
    queries = sorted({_folder(q) for q in table["query"]})
    references = sorted({_folder(r) for r in table["reference"]})
    per_query = table.groupby("query").size()
    low, high = int(per_query.min()), int(per_query.max())
    return {
        "sequence": sequence,
        "source": source,
        "traverse": f"{', '.join(queries)} vs {', '.join(references)}",
        "queries": table["query"].nunique(),
        "candidates": str(low) if low == high else f"{low}-{high}",
        "pairs": len(table),
        "positives": int(table["label"].sum()),
    }


def sequence_summary(
    output_dirs: Iterable[str | os.PathLike[str]], lists_dir: str | os.PathLike[str] | None = None
) -> pd.DataFrame:
    """Table II: each run folder's sequence, each official list in ``lists_dir`` (default: where ``data
    fetch gvbench-lists`` puts them) and the paper's text values of those sequences, each row labelled by its source."""
    from gvbench_nb.data import fetch

    rows = []
    folders = list(output_dirs)
    results = run_tables.load_results(folders) if folders else pd.DataFrame(columns=["output_dir"])
    for folder, group in results.groupby("output_dir", sort=False):
        table = run_tables.load_pairs_tables(folder, [group["method"].iloc[0]])[group["method"].iloc[0]]
        rows.append(count_pairs(str(group["sequence"].iloc[0]), table, RUN_COUNTED))
    text = reference_values.paper_sequences()
    lists = Path(lists_dir) if lists_dir else fetch.data_dir() / fetch.get_dataset("gvbench-lists").folder
    for name in text["sequence"]:
        path = lists / f"{name}.txt"
        if path.is_file():
            # The lists are checked by SHA-256 when fetched; pandas counts their 175,000 lines in
            # a second, where the pair-file parser's per-line checks take half a minute.
            pairs = pd.read_csv(path, sep=r"\s+", header=None, names=["query", "reference", "label"])
            rows.append(count_pairs(name, pairs, COUNTED))
    conditions = reference_values.paper_sequences().set_index("sequence")[["condition", "viewpoint"]]
    summary = pd.DataFrame(rows, columns=["sequence", "source", "traverse", *COUNTS])
    summary = pd.concat([summary.join(conditions, on="sequence"), text.assign(source=PAPER_TEXT)], ignore_index=True)
    order = {name: i for i, name in enumerate(dict.fromkeys(summary["sequence"]))}
    summary = summary.sort_values(["sequence", "source"], key=lambda c: c.map(order) if c.name == "sequence" else c)
    return summary.reindex(columns=SUMMARY_COLUMNS).reset_index(drop=True)


def summary_text(summary: pd.DataFrame) -> pd.DataFrame:
    """Table II for people: whole numbers with thousands separators, '-' where not stated."""

    def number(value: Any) -> str:
        return "-" if pd.isna(value) else f"{int(value):,}"

    text = summary.assign(**{c: summary[c].map(number) for c in ("queries", "pairs", "positives")})
    text["candidates"] = [c if isinstance(c, str) else number(c) for c in summary["candidates"]]
    return text.astype(object).fillna("-").replace("", "-")


def table_iii(results: pd.DataFrame, average: bool = True) -> pd.DataFrame:
    """Our AP and MR, one row a (method, profile), a column a (sequence, metric), then, with
    ``average`` and two sequences or more, the Average over them of each metric (NaN for a row
    missing a sequence)."""
    joined = results_table.join_paper_table(results, pd.DataFrame(), None)
    wide = results_table.results_table(joined).droplevel("source", axis=1)
    wide = wide.loc[:, wide.columns.get_level_values("metric").isin(run_tables.METRICS)]  # not the pairs column
    if average and results["sequence"].nunique() >= 2:
        for metric in run_tables.METRICS:
            wide[(AVERAGE, metric)] = wide.xs(metric, axis=1, level="metric").mean(axis=1, skipna=False)
    return wide


def real_and_synthetic(results: pd.DataFrame) -> tuple[pd.DataFrame, pd.DataFrame]:
    """The runs on recorded sequences, and those on routes the package rendered: the two are never
    averaged together (a rendered route measures the code, not a method's place in the paper)."""
    synthetic = results["synthetic"].astype(bool) if "synthetic" in results else pd.Series(False, index=results.index)
    return results[~synthetic], results[synthetic]


def places(table: pd.DataFrame, top: int = 3) -> pd.DataFrame:
    """Each cell's place in its column, 1 the highest (ties share a place), 0 below ``top`` or NaN."""
    ranks = table.apply(lambda column: pd.to_numeric(column, errors="coerce").rank(method="dense", ascending=False))
    return ranks.where(ranks <= top, 0).fillna(0).astype(int)


def style_table_iii(wide: pd.DataFrame) -> Any:
    """Table III in %: 1st bold, 2nd underlined, 3rd italic in each column (the paper's marking)."""
    marks = places(wide)
    styles = marks.map(lambda place: PLACE_STYLES.get(place, ""))
    shown = wide.rename(columns=run_tables.METRIC_HEADERS, level="metric")
    return (
        shown.style.format(lambda v: "-" if pd.isna(v) else f"{100 * v:.1f}")
        .apply(lambda _: styles.set_axis(shown.columns, axis=1), axis=None)
        .set_caption("1st bold, 2nd underlined, 3rd italic, in each column")
    )


def published_radar(source: str = run_tables.PAPER_LABEL) -> plt.Figure:
    """Fig. 1 of the published MR alone: the paper's table (or the GV-Bench repository's), every
    method it reports, each line labelled with its source; nothing of ours."""
    paper = source == run_tables.PAPER_LABEL
    table = results_table.load_paper_table() if paper else results_table.load_repository_table()
    frame = table.assign(method=table["paper_name"], source=source, profile="paper" if paper else "repository")
    return results_table.max_recall_radar(
        frame, title=f"max recall at 100% precision, published by the {source} (values as published)"
    )


def method_across_sequences(results: pd.DataFrame) -> plt.Figure:
    """Fig. 8's grouping: a group a (method, profile), a bar a sequence, MR and AP panels."""
    sequences = list(dict.fromkeys(results["sequence"]))
    rows = list(dict.fromkeys(zip(results["method"], results["profile"])))
    colours = plots.method_colours(sequences)
    width = 0.8 / len(sequences)
    figure, axes = plt.subplots(2, 1, figsize=(max(8.0, 1.2 * len(rows) * max(1, len(sequences) / 3)), 6.5))
    for axis, metric in zip(axes, ("max_recall", "ap")):
        for i, sequence in enumerate(sequences):
            data = results[results["sequence"] == sequence].set_index(["method", "profile"])[metric]
            values = [100 * data.get(row, np.nan) for row in rows]
            axis.bar(np.arange(len(rows)) + i * width, values, width, color=colours[sequence], label=sequence)
        labels = [plots.run_label(m, p).replace(" (", "\n(", 1) for m, p in rows]
        axis.set_xticks(np.arange(len(rows)) + 0.4 - width / 2, labels, fontsize=8)
        axis.set(ylabel=run_tables.METRIC_HEADERS[metric], ylim=(0, 105))
    axes[0].legend(title="sequence", fontsize=8, loc="upper left", bbox_to_anchor=(1.0, 1.0))
    figure.suptitle("Each method across sequences (ours; the paper's Fig. 8 grouping)")
    figure.tight_layout()
    return figure
