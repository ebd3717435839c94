"""Figures of the analysis notebooks (the paper's Figs. 1, 6-9 and our uncertainty plot).

Every figure is drawn from tables that ``analysis.py`` computes from written results;
the paper's numbers, where shown, are labelled "paper".
"""

from __future__ import annotations

import os
from collections.abc import Sequence as SequenceType
from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np
import pandas as pd
from matplotlib.ticker import NullFormatter, ScalarFormatter

from gvbench_nb.evaluation import analysis
from gvbench_nb.protocol.images import read_image
from gvbench_nb.reporting import plots

STAGE_LABELS = {
    "extract_seconds_per_pair": "extraction (amortised)",
    "match_seconds_per_pair": "matching",
    "verify_seconds_per_pair": "verification (RANSAC)",
}
SOURCE_STYLE = {
    analysis.OURS_LABEL: {"linestyle": "-", "alpha": 0.9},
    analysis.PAPER_LABEL: {"linestyle": "--", "alpha": 0.6},
    analysis.REPOSITORY_LABEL: {"linestyle": ":", "alpha": 0.6},
}
# Ours under a second profile is told apart from the first by its line, as the label says.
OURS_PROFILE_STYLE = {"paper": "-", "repository": "-."}


def _line_style(source: str, profile: str) -> dict:
    style = dict(SOURCE_STYLE[source])
    if source == analysis.OURS_LABEL:
        style["linestyle"] = OURS_PROFILE_STYLE.get(profile, "-")
    return style


def run_label(method: str, profile: str, sequence: str | None = None) -> str:
    """'method [profile]' (and the sequence when given): how a run is named in figures."""
    return f"{method} [{profile}]" + (f" ({sequence})" if sequence else "")


def _method_colours(methods: SequenceType[str]) -> dict[str, tuple]:
    palette = plt.get_cmap("tab10")
    return {m: palette(i % 10) for i, m in enumerate(methods)}


def max_recall_radar(joined: pd.DataFrame, title: str = "") -> plt.Figure:
    """MR of every (method, profile) across sequences (the paper's Fig. 1): ours solid (the
    repository profile dash-dotted), the paper's dashed, the GV-Bench repository's dotted;
    every line's label names its source and profile.

    A radar needs three sequences or more; with fewer the same values are drawn as bars.
    """
    sequences = list(dict.fromkeys(joined["sequence"]))
    methods = list(dict.fromkeys(joined["method"]))
    colours = _method_colours(methods)
    if len(sequences) < 3:
        return _max_recall_bars(joined, sequences, methods, colours, title)
    angles = np.linspace(0, 2 * np.pi, len(sequences), endpoint=False)
    figure, axis = plt.subplots(figsize=(6.5, 6.5), subplot_kw={"projection": "polar"})
    for (method, profile, source), group in joined.groupby(["method", "profile", "source"], sort=False):
        values = group.set_index("sequence")["max_recall"].reindex(sequences).to_numpy(dtype=float)
        if np.isnan(values).all():
            continue
        closed = np.r_[values, values[:1]]
        axis.plot(
            np.r_[angles, angles[:1]],
            closed,
            color=colours[method],
            marker="o",
            markersize=3,
            label=f"{method} ({analysis.source_label(source, profile)})",
            **_line_style(source, profile),
        )
    axis.set_xticks(angles, sequences)
    axis.set_ylim(0, max(0.05, float(np.nanmax(joined["max_recall"])) * 1.1))
    axis.set_title(title or "max recall at 100% precision across sequences", pad=20)
    axis.legend(loc="upper left", bbox_to_anchor=(1.05, 1.0), fontsize=8)
    return figure


def _max_recall_bars(
    joined: pd.DataFrame, sequences: list[str], methods: list[str], colours: dict, title: str
) -> plt.Figure:
    """One bar a (method, profile, source) and sequence, each labelled with its source and profile."""
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
            axis.barh(
                row,
                value.iloc[0],
                height=0.8,
                color=colours[method],
                hatch=None if source == analysis.OURS_LABEL else "//",
                alpha=SOURCE_STYLE[source]["alpha"],
                edgecolor="black",
                linewidth=0.4,
            )
            axis.text(value.iloc[0], row, f" {100 * value.iloc[0]:.1f}%", va="center", fontsize=7)
        axis.set_yticks(range(len(rows)), [f"{m} ({analysis.source_label(src, p)})" for m, p, src in rows], fontsize=7)
        axis.invert_yaxis()
        axis.set(title=sequence, xlabel="max recall at 100% precision", xlim=(0, 1.15))
    figure.suptitle(
        (title + "\n" if title else "") + "(a radar needs 3+ sequences: bars; hatched: published)", fontsize=10
    )
    figure.tight_layout()
    return figure


def seconds_per_pair_stacked(runtime: pd.DataFrame, caption: str = "") -> plt.Figure:
    """Seconds per pair by stage, stacked, one bar a (sequence, profile, method)."""
    several = runtime["sequence"].nunique() > 1
    labels = [
        run_label(m, p, s if several else None)
        for s, p, m in zip(runtime["sequence"], runtime["profile"], runtime["method"])
    ]
    figure, axis = plt.subplots(figsize=(7, 0.45 * len(runtime) + 1.8))
    left = np.zeros(len(runtime))
    for column, label in STAGE_LABELS.items():
        values = runtime[column].to_numpy(dtype=float)
        axis.barh(labels, values, left=left, label=label)
        left += values
    for row, total in enumerate(left):
        axis.text(total, row, f" {total * 1000:.0f} ms", va="center", fontsize=8)
    axis.invert_yaxis()
    axis.set(xlabel="seconds per pair", xlim=(0, left.max() * 1.2 if len(left) else 1))
    axis.legend(fontsize=8, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    axis.set_title("where the time goes", fontsize=11)
    if caption:
        figure.text(0.01, -0.02, caption, fontsize=7, va="top", wrap=True)
    figure.tight_layout()
    return figure


def fps_vs_max_recall(runtime: pd.DataFrame, caption: str = "") -> plt.Figure:
    """FPS (pairs verified a second, 1 / seconds per pair) against MR (the paper's Fig. 7),
    one point a (sequence, profile, method), labelled with its profile."""
    figure, axis = plt.subplots(figsize=(6.5, 4.5))
    colours = _method_colours(list(dict.fromkeys(runtime["method"])))
    markers = dict(zip(dict.fromkeys(runtime["sequence"]), "osD^vP*X"))
    for row in runtime.itertuples():
        axis.scatter(
            row.fps,
            row.max_recall,
            color=colours[row.method],
            marker=markers[row.sequence],
            s=60,
            edgecolor="black",
            linewidth=0.5,
        )
        sequence = row.sequence if runtime["sequence"].nunique() > 1 else None
        axis.annotate(
            run_label(row.method, row.profile, sequence),
            (row.fps, row.max_recall),
            textcoords="offset points",
            xytext=(5, 4),
            fontsize=8,
        )
    axis.set_xscale("log")
    # At least a decade shown, so a log axis keeps readable ticks.
    low, high = float(runtime["fps"].min()), float(runtime["fps"].max())
    middle = np.sqrt(low * high)
    span = max(np.sqrt(high / low) * 1.5, np.sqrt(10))
    axis.set_xlim(middle / span, middle * span)
    axis.xaxis.set_major_formatter(ScalarFormatter())
    axis.xaxis.set_minor_formatter(NullFormatter())
    axis.set(
        xlabel="FPS (pairs a second, 1 / seconds per pair; log scale)",
        ylabel="max recall at 100% precision",
        ylim=(-0.02, max(0.1, float(runtime["max_recall"].max()) * 1.2)),
    )
    axis.grid(alpha=0.3, which="both")
    axis.set_title("speed vs max recall", fontsize=11)
    figure.tight_layout()
    if caption:
        figure.text(0.01, 0.0, caption, fontsize=7, va="top", wrap=True)
    return figure


def normalised_inlier_histograms(tables: dict[str, pd.DataFrame], title: str = "", bins: int = 30) -> plt.Figure:
    """Normalised inlier counts of true vs false pairs, one panel a run (Figs. 6, 8, 9), titled
    with its method and profile (from the table's ``profile`` column).

    Shaded: above the top false pair's score, where every true pair counts towards MR;
    annotated: the share of true pairs with zero inliers (unreachable at any threshold).
    """
    n = len(tables)
    columns = min(n, 3)
    rows = int(np.ceil(n / columns))
    figure, axes = plt.subplots(rows, columns, figsize=(4.6 * columns, 3.2 * rows), squeeze=False)
    edges = np.linspace(0, 1, bins + 1)
    for axis, (method, table) in zip(axes.ravel(), tables.items()):
        normalised = analysis.normalised_inliers(table)
        summary = analysis.inlier_overlap_summary(table)
        for label, name, colour in ((1, "true", "tab:green"), (0, "false", "tab:red")):
            axis.hist(
                normalised[table["label"] == label],
                bins=edges,
                color=colour,
                alpha=0.55,
                label=f"{name} ({int((table['label'] == label).sum())})",
                density=True,
            )
        top = summary["top_false_normalised"]
        axis.axvspan(top, 1.0, color="tab:blue", alpha=0.08)
        axis.axvline(top, color="tab:blue", linestyle="--", linewidth=1)
        axis.text(
            0.98,
            0.95,
            f"true pairs above top false: {summary['true_above_top_false']:.1%} (= MR)\n"
            f"true pairs with 0 inliers: {summary['true_zero_inliers']:.1%}",
            transform=axis.transAxes,
            ha="right",
            va="top",
            fontsize=7,
            bbox={"facecolor": "white", "alpha": 0.8, "edgecolor": "none"},
        )
        profiles = table["profile"].unique() if "profile" in table else []
        if len(profiles) > 1:
            raise ValueError(
                f"the pairs table of {method!r} mixes profiles {sorted(profiles)}; "
                "give each profile's table its own key"
            )
        panel = run_label(method, profiles[0]) if len(profiles) else method
        axis.set(title=panel, xlabel="inliers / method's max inliers", ylabel="density")
        axis.legend(fontsize=7, loc="center right")
    for axis in axes.ravel()[n:]:
        axis.axis("off")
    if title:
        figure.suptitle(title)
    figure.tight_layout()
    return figure


def failure_pairs(
    rows: pd.DataFrame,
    output_dir: str | os.PathLike[str],
    method: str,
    image_root: str | os.PathLike[str],
    cache_dir: str | os.PathLike[str] | None = None,
    title: str = "",
) -> plt.Figure:
    """Each pair of ``rows`` (a failures table) drawn with inlier matches green, outliers red."""
    figure, axes = plt.subplots(len(rows), 1, figsize=(10, 3.4 * max(len(rows), 1)), squeeze=False)
    for axis, row in zip(axes[:, 0], rows.itertuples()):
        lines = analysis.match_lines(output_dir, method, row.query, row.reference, cache_dir)
        image0 = read_image(Path(image_root) / row.query)
        image1 = read_image(Path(image_root) / row.reference)
        plots.draw_matches(image0, image1, lines["points0"], lines["points1"], lines["inlier_mask"], axis=axis)
        offsets = [f"{row.frame_offset:.0f} frames" if not pd.isna(getattr(row, "frame_offset", np.nan)) else ""]
        if hasattr(row, "distance_m"):
            offsets.append(f"{row.distance_m:.1f} m, {row.heading_deg:.0f} deg")
        kind = "false positive" if row.label == 0 else "false negative"
        axis.set_title(
            f"{kind} #{row.rank}: {row.query} | {row.reference}  score {row.score:g} inliers "
            f"of {row.num_matches} matches; ground-truth offset {', '.join(o for o in offsets if o)}",
            fontsize=8,
        )
    if title:
        figure.suptitle(title)
    figure.tight_layout()
    return figure


def bootstrap_intervals(intervals: pd.DataFrame, title: str = "") -> plt.Figure:
    """Point estimate and 95% percentile CI of AP and MR, one row a method."""
    metrics = list(dict.fromkeys(intervals["metric"]))
    figure, axes = plt.subplots(
        1,
        len(metrics),
        figsize=(5 * len(metrics), 0.45 * intervals["method"].nunique() + 1.8),
        squeeze=False,
        sharey=True,
    )
    for axis, metric in zip(axes[0], metrics):
        data = intervals[intervals["metric"] == metric].reset_index(drop=True)
        y = np.arange(len(data))
        errors = np.vstack([data["estimate"] - data["low"], data["high"] - data["estimate"]])
        axis.errorbar(data["estimate"], y, xerr=np.clip(errors, 0, None), fmt="o", capsize=4, color="tab:blue")
        for i, row in data.iterrows():
            axis.text(
                row["high"],
                i,
                f"  {row['estimate']:.1%} [{row['low']:.1%}, {row['high']:.1%}]",
                va="center",
                fontsize=7,
            )
        axis.set_yticks(y, data["method"])
        axis.set_xticks(np.linspace(0, 1, 6))
        axis.set(xlabel=f"{metric} (95% CI, queries resampled)", xlim=(0, 1.35))
        axis.grid(alpha=0.3, axis="x")
    axes[0, 0].invert_yaxis()  # once: the axes share y, so a second call would undo it
    if title:
        figure.suptitle(title)
    figure.tight_layout()
    return figure
