"""What notebooks/analysis_results_table.ipynb computes and draws: our results beside the paper's and
the GV-Bench repository's published tables (always labelled as theirs), and the max-recall chart.
"""

from __future__ import annotations

import os
from collections.abc import Iterable
from collections.abc import Sequence as SequenceType
from pathlib import Path
from typing import Any

import matplotlib.pyplot as plt
import numpy as np
import pandas as pd

from gvbench_nb import methods as method_registry
from gvbench_nb.evaluation import plots, reference_values, run_tables
from gvbench_nb.runner.score_files import IMPORTED_PROFILE


def load_paper_table(path: str | os.PathLike[str] | None = None) -> pd.DataFrame:
    """The paper's AP/MR as fractions, with our method names where we have them (None elsewhere); ``path``:
    a file in the shipped format (``method,sequence,ap,max_recall`` in %), empty when absent."""
    columns = ["paper_name", "method", "sequence", *run_tables.METRICS]
    if path is None:
        table = reference_values.paper_table()
    elif not Path(path).is_file():
        return pd.DataFrame(columns=columns)
    else:
        table = reference_values.paper_table(pd.read_csv(path), where=str(path))
    return table.rename(columns={"reference_name": "paper_name"})[columns]


def load_repository_table() -> pd.DataFrame:
    """The GV-Bench repository's published AP/MR (fractions), its matcher names as ``paper_name``
    and ours as ``method`` where they are the same method (``reference_values.REPOSITORY_METHODS``);
    its sequences in the paper's order, so the two published tables and radars line up."""
    table = reference_values.repository_table().rename(columns={"reference_name": "paper_name"})
    order = {name: i for i, name in enumerate(dict.fromkeys(reference_values.paper_table()["sequence"]))}
    place = table["sequence"].map(order).fillna(len(order))
    return table.iloc[np.argsort(place.to_numpy(), kind="stable")].reset_index(drop=True)


def line_label(method: str, profile: str, source: str) -> str:
    """How a row's values are named in figures: ours as every run is ('sift-nn (repository profile)',
    'my-tool (imported)'), a published value by its source ('SIFT+NN (paper)')."""
    return plots.run_label(method, profile) if source == run_tables.OURS_LABEL else f"{method} ({source})"


def join_paper_table(
    results: pd.DataFrame, paper: pd.DataFrame, repository: pd.DataFrame | None = None
) -> pd.DataFrame:
    """Long table of ours and the published values, one row a (method, profile, sequence, source); a
    published value is kept only beside a run of the same method, sequence and profile. Two runs
    with the same (sequence, profile, method) are an error."""
    if "profile" not in results:
        raise ValueError(
            "the results have no profile column: evaluate the runs again "
            "(python -m gvbench_nb run PARAMS) so each run records its profile"
        )
    twice = results[results.duplicated(run_tables.RUN_KEY, keep=False)]
    if not twice.empty:
        where = twice.get("output_dir", pd.Series(["?"] * len(twice), index=twice.index))
        runs = "; ".join(f"{r.sequence}/{r.profile}/{r.method} in {w}" for r, w in zip(twice.itertuples(), where))
        raise ValueError(
            f"the same (sequence, profile, method) appears more than once: {runs}; pass only one output folder for each"
        )
    ours = results[["method", "profile", "sequence", *run_tables.METRICS]].copy()
    if "n_pairs" in results:
        limits = results["limit"] if "limit" in results else [None] * len(results)
        ours["pairs"] = [pairs_text(n, limit) for n, limit in zip(results["n_pairs"], limits)]
    # As the run recorded it (an imported method's ends in '(imported)'), else the registry's.
    recorded = results["paper_name"] if "paper_name" in results else pd.Series(np.nan, index=results.index)
    ours["paper_name"] = recorded.fillna(ours["method"].map(method_registry.paper_name))
    ours["source"] = run_tables.OURS_LABEL
    ran = set(zip(ours["method"], ours["sequence"], ours["profile"]))
    frames = [ours]
    for table, source, profile in (
        (paper, run_tables.PAPER_LABEL, "paper"),
        (repository, run_tables.REPOSITORY_LABEL, "repository"),
    ):
        if table is None or table.empty:
            continue
        # A boolean array, not a list: an empty list would select no columns instead of no rows.
        keep = np.array([(m, s, profile) in ran for m, s in zip(table["method"], table["sequence"])], dtype=bool)
        frames.append(table[keep].assign(source=source, profile=profile))
    columns = ["method", "paper_name", "profile", "sequence", "source", *run_tables.METRICS]
    columns += ["pairs"] if "pairs" in ours else []
    joined = pd.concat([f.reindex(columns=columns) for f in frames], ignore_index=True)
    joined["label"] = [line_label(*row) for row in zip(joined["method"], joined["profile"], joined["source"])]
    return joined


def pairs_text(n_pairs: int, limit: int | None) -> str:
    """How many pairs a run scored, and whether ``--limit`` cut the pair file: '240 (all)', '24 (--limit)'."""
    cut = limit is not None and not pd.isna(limit)
    return "-" if pd.isna(n_pairs) else f"{int(n_pairs)} ({'--limit' if cut else 'all'})"


def results_table(joined: pd.DataFrame, metrics: SequenceType[str] = run_tables.METRICS) -> pd.DataFrame:
    """Wide table, a row a (method, profile), columns (sequence, metric, source): ours beside the published
    values of the same protocol, and our ``pairs``; first-seen order."""
    values = ["pairs", *metrics] if "pairs" in joined else list(metrics)
    wide = _by_sequence(joined, ["method", "profile"], values)
    row_order = [r for r in dict.fromkeys(zip(joined["method"], joined["profile"])) if r in wide.index]
    wide = wide.loc[row_order]
    wide.index = pd.MultiIndex.from_tuples([(row_label(m, p), p) for m, p in wide.index], names=["method", "profile"])
    return wide


def row_label(method: str, profile: str) -> str:
    """A table row's method: with the paper's name where it has another ('sift-nn (SIFT+NN)'),
    an imported method as every view names it ('my-tool (imported)')."""
    if profile == IMPORTED_PROFILE:
        return plots.run_label(method, profile)
    name = method_registry.paper_name(method)
    return method if name == method else f"{method} ({name})"


def _by_sequence(table: pd.DataFrame, index: str | list[str], values: list[str]) -> pd.DataFrame:
    """``values`` pivoted to columns (sequence, metric, source): sequences first-seen, then ``values``'
    order, ours before the published; a column without any value is left out."""
    wide = table.pivot_table(index=index, columns=["sequence", "source"], values=values, aggfunc="first")
    sources = [run_tables.OURS_LABEL, run_tables.PAPER_LABEL, run_tables.REPOSITORY_LABEL]
    keys = [
        (s, m, src)
        for s in dict.fromkeys(table["sequence"])
        for m in values
        for src in sources
        if (m, s, src) in wide.columns
    ]
    wide = wide[[(m, s, src) for s, m, src in keys]]
    wide.columns = pd.MultiIndex.from_tuples(keys, names=["sequence", "metric", "source"])
    return wide


def paper_reference_table(
    paper: pd.DataFrame, methods: Iterable[str] | None = None, source: str = run_tables.PAPER_LABEL
) -> pd.DataFrame:
    """A published table (all its sequences) for ``methods`` (its own names kept for the
    methods we do not implement when ``methods`` is None), columns (sequence, metric, source)."""
    if methods is not None:
        paper = paper[paper["method"].isin(list(methods))]
    wide = _by_sequence(paper.assign(source=source), "paper_name", list(run_tables.METRICS))
    # Its rows are the publication's own method names.
    return wide.loc[list(dict.fromkeys(paper["paper_name"]))].rename_axis(run_tables.HEADERS["paper_name"])


def metric_columns(wide: pd.DataFrame) -> list[tuple]:
    """The wide table's AP and MR columns (not its 'pairs' ones)."""
    return [c for c in wide.columns if c[1] in run_tables.METRICS]


def style_results_table(wide: pd.DataFrame) -> Any:
    """The wide table as a pandas Styler: values in % under 'AP (%)' and 'MR (%)', each column's
    best in bold, the published columns (paper, GV-Bench repository) in grey italics."""
    metrics = metric_columns(wide)
    best = run_tables.best_per_column(wide[metrics]).reindex(columns=wide.columns, fill_value=False)
    styles = pd.DataFrame("", index=wide.index, columns=wide.columns)
    for column in wide.columns:
        paper = column[-1] in (run_tables.PAPER_LABEL, run_tables.REPOSITORY_LABEL)
        base = "color: #666; font-style: italic;" if paper else ""
        styles[column] = [base + ("font-weight: bold;" if b else "") for b in best[column]]
    shown = wide.rename(columns=run_tables.METRIC_HEADERS, level="metric")
    in_percent = [shown.columns[wide.columns.get_loc(c)] for c in metrics]
    # A run missing a sequence has no pairs there: "-", as its AP and MR.
    styler = shown.style.format(na_rep="-").format(_percent, subset=in_percent)
    return styler.apply(lambda _: styles.set_axis(shown.columns, axis=1), axis=None)


def _percent(value: float) -> str:
    return "-" if pd.isna(value) else f"{100 * value:.1f}"


SOURCE_STYLE = {
    run_tables.OURS_LABEL: {"linestyle": "-", "alpha": 0.9},
    run_tables.PAPER_LABEL: {"linestyle": "--", "alpha": 0.6},
    run_tables.REPOSITORY_LABEL: {"linestyle": ":", "alpha": 0.6},
}


# Ours under a second profile is told apart from the first by its line, as the label says.
OURS_PROFILE_STYLE = {"paper": "-", "repository": "-."}


def _line_style(source: str, profile: str) -> dict:
    style = dict(SOURCE_STYLE[source])
    if source == run_tables.OURS_LABEL:
        style["linestyle"] = OURS_PROFILE_STYLE.get(profile, "-")
    return style


def max_recall_radar(joined: pd.DataFrame, title: str = "") -> plt.Figure:
    """MR in % of every (method, profile) across sequences (Fig. 1), each line labelled with its source and
    profile: a radar over the sequences every line has (a line never cuts across a missing vertex; the
    others are named under it), bars of every value when fewer than three are left."""
    sequences = list(dict.fromkeys(joined["sequence"]))
    methods = list(dict.fromkeys(joined["method"]))
    colours = plots.method_colours(methods)
    title = title or "max recall at 100% precision (%)"
    lines = joined.pivot_table(
        index=["method", "profile", "source"], columns="sequence", values="max_recall", aggfunc="first"
    )
    shared = [s for s in sequences if s in lines and lines[s].notna().all()]
    if len(shared) < 3:
        return _max_recall_bars(joined, sequences, methods, colours, title)
    angles = np.linspace(0, 2 * np.pi, len(shared), endpoint=False)
    figure, axis = plt.subplots(figsize=(6.5, 6.5), subplot_kw={"projection": "polar"})
    for (method, profile, source), group in joined.groupby(["method", "profile", "source"], sort=False):
        values = 100 * group.set_index("sequence")["max_recall"].reindex(shared).to_numpy(dtype=float)
        axis.plot(
            np.r_[angles, angles[:1] + 2 * np.pi], np.r_[values, values[:1]], color=colours[method], marker="o",
            markersize=3, label=line_label(method, profile, source), **_line_style(source, profile),
        )  # fmt: skip
    axis.set_xticks(angles, shared)
    axis.set_ylim(0, max(5.0, 110 * float(np.nanmax(joined["max_recall"]))))
    axis.set_title(title, pad=20)
    axis.legend(loc="upper left", bbox_to_anchor=(1.05, 1.0), fontsize=8)
    left_out = [s for s in sequences if s not in shared]
    if left_out:
        note = f"not drawn, as not every line has it (the tables have it): {', '.join(left_out)}"
        figure.text(0.02, 0.02, note, fontsize=8)
    return figure


def _max_recall_bars(
    joined: pd.DataFrame, sequences: list[str], methods: list[str], colours: dict, title: str
) -> plt.Figure:
    """One bar a (method, profile, source) and sequence, in %, each labelled with its source and profile."""
    rows = list(dict.fromkeys(zip(joined["method"], joined["profile"], joined["source"])))
    figure, axes = plt.subplots(
        1, len(sequences), figsize=(4.5 * len(sequences), 0.4 * len(rows) + 2), squeeze=False, sharex=True
    )
    for axis, sequence in zip(axes[0], sequences):
        data = joined[joined["sequence"] == sequence]
        for row, (method, profile, source) in enumerate(rows):
            value = data[(data.method == method) & (data.profile == profile) & (data.source == source)]["max_recall"]
            if value.empty:
                continue
            percent = 100 * float(value.iloc[0])
            style = {"color": colours[method], "alpha": SOURCE_STYLE[source]["alpha"], "edgecolor": "black"}
            hatch = None if source == run_tables.OURS_LABEL else "//"
            axis.barh(row, percent, height=0.8, hatch=hatch, linewidth=0.4, **style)
            axis.text(percent, row, f" {percent:.1f}%", va="center", fontsize=7)
        axis.set_yticks(range(len(rows)), [line_label(*row) for row in rows], fontsize=7)
        axis.invert_yaxis()
        axis.set(title=sequence, xlabel="max recall at 100% precision (%)", xlim=(0, 115))
    published = (joined["source"] != run_tables.OURS_LABEL).any()
    figure.suptitle(title + ("; hatched: published values" if published else ""), fontsize=10)
    figure.tight_layout()
    return figure
