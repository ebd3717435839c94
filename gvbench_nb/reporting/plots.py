"""Figures the notebooks show and save as PNG; data comes only from written results."""

from __future__ import annotations

from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np
import pandas as pd
from matplotlib.colors import to_rgba

from gvbench_nb.data.images import read_image
from gvbench_nb.evaluation.metrics import max_recall_at_full_precision, pr_curve
from gvbench_nb.runner import record


def save(figure: plt.Figure, path: str | Path) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    # Never over a file of an output folder that the package did not write; recorded as its own after.
    return record.save_checked(path, lambda target: figure.savefig(target, dpi=120, bbox_inches="tight"))


def pr_curves(tables: dict[str, pd.DataFrame], title: str = "") -> plt.Figure:
    """PR curve per method with its MR (recall at precision 1.0) marked."""
    figure, axis = plt.subplots(figsize=(6.5, 5))
    for method, table in tables.items():
        labels, scores = table["label"].to_numpy(), table["score"].to_numpy()
        curve = pr_curve(labels, scores, where=method)
        max_recall = max_recall_at_full_precision(labels, scores, where=method)
        (line,) = axis.plot(curve["recall"], curve["precision"], label=f"{method} (MR {max_recall:.1%})")
        axis.plot([max_recall], [1.0], marker="o", color=line.get_color(), markersize=7)
    axis.set(xlabel="recall", ylabel="precision", xlim=(0, 1.01), ylim=(0, 1.03), title=title or "precision-recall")
    axis.grid(alpha=0.3)
    axis.legend(loc="lower left", fontsize=8)
    return figure


def inlier_histogram(table: pd.DataFrame, title: str = "") -> plt.Figure:
    """Inlier counts of true vs false pairs: the overlap is what caps MR."""
    # matplotlib's step histograms, not seaborn's: importing seaborn costs a stage notebook
    # more than drawing this figure does.
    figure, axis = plt.subplots(figsize=(6.5, 3.5))
    bins = np.histogram_bin_edges(table["num_inliers"], bins=min(40, max(5, table["num_inliers"].nunique())))
    for label, name, colour in ((1, "true loop closure", "tab:blue"), (0, "false", "tab:orange")):
        inliers = table.loc[table["label"] == label, "num_inliers"]
        if len(inliers):
            axis.hist(
                inliers,
                bins=bins.tolist(),
                histtype="stepfilled",
                facecolor=to_rgba(colour, 0.25),
                edgecolor=colour,
                label=name,
            )
    axis.set(xlabel="RANSAC inliers (score)", ylabel="Count", title=title)
    axis.legend(title="pair")
    return figure


def example_pairs(image_root: Path, pairs: pd.DataFrame, n: int = 4, title: str = "") -> plt.Figure:
    """Query beside reference for a few pairs, labelled true or false."""
    rows = pairs.head(n)
    figure, axes = plt.subplots(len(rows), 2, figsize=(8, 2.6 * len(rows)), squeeze=False)
    for axis_row, (_, row) in zip(axes, rows.iterrows()):
        for axis, name in zip(axis_row, (row["query"], row["reference"])):
            axis.imshow(read_image(Path(image_root) / name))
            axis.set_title(name, fontsize=8)
            axis.axis("off")
        axis_row[0].text(
            -0.02,
            0.5,
            "true" if row["label"] == 1 else "false",
            transform=axis_row[0].transAxes,
            rotation=90,
            va="center",
            ha="right",
            fontsize=11,
            color="green" if row["label"] == 1 else "red",
        )
    if title:
        figure.suptitle(title)
    figure.tight_layout()
    return figure


def positives_per_query(pairs: pd.DataFrame, title: str = "") -> plt.Figure:
    counts = pairs.groupby("query")["label"].sum()
    figure, axis = plt.subplots(figsize=(5, 3))
    # As a list: matplotlib's stubs take a Sequence of edges, not an array.
    axis.hist(counts, bins=(np.arange(counts.max() + 2) - 0.5).tolist(), color="tab:blue")
    axis.set(xlabel="true references a query", ylabel="queries", title=title)
    return figure


def draw_matches(
    image0: np.ndarray,
    image1: np.ndarray,
    points0: np.ndarray,
    points1: np.ndarray,
    inlier_mask: np.ndarray,
    axis: plt.Axes | None = None,
    max_lines: int = 300,
) -> plt.Axes:
    """Side by side with inlier matches green and outliers red."""
    height = max(image0.shape[0], image1.shape[0])
    canvas = np.zeros((height, image0.shape[1] + image1.shape[1], 3), dtype=np.uint8)
    canvas[: image0.shape[0], : image0.shape[1]] = image0 if image0.ndim == 3 else image0[..., None]
    canvas[: image1.shape[0], image0.shape[1] :] = image1 if image1.ndim == 3 else image1[..., None]
    axis = axis or plt.subplots(figsize=(10, 4))[1]
    axis.imshow(canvas)
    order = np.argsort(~inlier_mask)[:max_lines]
    for index in order:
        (x0, y0), (x1, y1) = points0[index], points1[index]
        axis.plot(
            [x0, x1 + image0.shape[1]],
            [y0, y1],
            color="lime" if inlier_mask[index] else "red",
            linewidth=0.6,
            alpha=0.8,
        )
    axis.axis("off")
    return axis
