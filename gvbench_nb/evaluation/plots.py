"""Figures the notebooks show and save as PNG; data comes only from written results."""

from __future__ import annotations

from collections.abc import Sequence as SequenceType
from pathlib import Path
from typing import Any

import cv2
import matplotlib.pyplot as plt
import numpy as np
import pandas as pd
from matplotlib.colors import to_rgba

from gvbench_nb.evaluation import collapsed_inliers
from gvbench_nb.protocol.images import read_image
from gvbench_nb.protocol.metrics import average_precision, max_recall_at_full_precision, pr_curve
from gvbench_nb.runner.score_files import IMPORTED_PROFILE


def save(figure: plt.Figure, path: str | Path) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    temporary = path.with_name(f".{path.stem}.tmp{path.suffix}")  # a reader never sees half a figure
    figure.savefig(temporary, dpi=120, bbox_inches="tight")
    return temporary.replace(path)


def _pr_curve(axis: plt.Axes, table: pd.DataFrame, where: str, **style: Any) -> Any:
    """One PR curve with its MR dotted at precision 1, labelled ``where``: AP and MR in %."""
    labels, scores = table["label"].to_numpy(), table["score"].to_numpy()
    curve = pr_curve(labels, scores, where=where)
    max_recall = max_recall_at_full_precision(labels, scores, where=where)
    ap = average_precision(labels, scores, where=where)
    label = f"{where}: AP {100 * ap:.1f}%, MR {100 * max_recall:.1f}%"
    (line,) = axis.plot(curve["recall"], curve["precision"], label=label, **style)
    axis.plot([max_recall], [1.0], marker="o", color=line.get_color(), markersize=7)
    return line


def _pr_axes(axis: plt.Axes, title: str) -> None:
    axis.set(xlabel="recall", ylabel="precision", xlim=(0, 1.01), ylim=(0, 1.03), title=title or "precision-recall")
    axis.grid(alpha=0.3)
    axis.legend(loc="lower left", fontsize=8)


def pr_curves(tables: dict[str, pd.DataFrame], title: str = "") -> plt.Figure:
    """PR curve per method with its MR (recall at precision 1.0) marked."""
    figure, axis = plt.subplots(figsize=(6.5, 5))
    for method, table in tables.items():
        _pr_curve(axis, table, method)
    _pr_axes(axis, title)
    return figure


PROFILE_LINE_STYLES = {"repository": "-", "paper": "--"}  # a profile's curves share a line style


def pr_curves_by_profile(tables: dict[tuple[str, str], pd.DataFrame], title: str = "") -> plt.Figure:
    """PR curve per (method, profile) of one sequence, MR marked: a method keeps its colour
    across profiles and a profile its line style; each label names both."""
    figure, axis = plt.subplots(figsize=(7, 5.5))
    colours: dict[str, Any] = {}
    for (method, profile), table in tables.items():
        style = {"color": colours.get(method), "linestyle": PROFILE_LINE_STYLES.get(profile, ":")}
        line = _pr_curve(axis, table, run_label(method, profile), **style)
        colours.setdefault(method, line.get_color())
    _pr_axes(axis, title)
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
            axis.hist(inliers, bins=bins.tolist(), histtype="stepfilled", facecolor=to_rgba(colour, 0.25),
                      edgecolor=colour, label=name)  # fmt: skip
    axis.set(xlabel="RANSAC inliers (score)", ylabel="Count", title=title)
    axis.legend(title="pair")
    return figure


def example_pairs(image_root: Path, pairs: pd.DataFrame, n: int = 4, title: str = "") -> plt.Figure:
    """Query beside reference for a few pairs, labelled true or false."""
    rows = pairs.head(n)
    figure, axes = plt.subplots(len(rows), 2, figsize=(8, 2.6 * len(rows)), squeeze=False)
    for axis_row, (_, row) in zip(axes, rows.iterrows()):
        for axis, name in zip(axis_row, (row["query"], row["reference"])):
            image = read_image(Path(image_root) / name)
            # Shrunk to about the pixels the panel has (4 in at 120 dpi): drawing full-size photos is slow.
            scale = min(1.0, 480 / image.shape[1])
            if scale < 1.0:
                image = cv2.resize(image, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
            axis.imshow(image)
            axis.set_title(name, fontsize=8)
            axis.axis("off")
        word, colour = ("true", "green") if row["label"] == 1 else ("false", "red")
        first = axis_row[0]
        first.text(
            -0.02, 0.5, word, transform=first.transAxes, rotation=90, va="center", ha="right", fontsize=11, color=colour
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


MATCH_GAP = 12  # white pixels between the two images of a pair, so their edges do not touch


def match_canvas(image0: np.ndarray, image1: np.ndarray, gap: int = MATCH_GAP) -> tuple[np.ndarray, int]:
    """The two images side by side on white, ``gap`` pixels apart; returns the canvas and
    the x offset of the second image."""
    height = max(image0.shape[0], image1.shape[0])
    offset = image0.shape[1] + gap
    canvas = np.full((height, offset + image1.shape[1], 3), 255, dtype=np.uint8)
    canvas[: image0.shape[0], : image0.shape[1]] = image0 if image0.ndim == 3 else image0[..., None]
    canvas[: image1.shape[0], offset:] = image1 if image1.ndim == 3 else image1[..., None]
    return canvas, offset


def draw_matches(
    image0: np.ndarray,
    image1: np.ndarray,
    points0: np.ndarray,
    points1: np.ndarray,
    inlier_mask: np.ndarray,
    axis: plt.Axes | None = None,
    max_lines: int = 300,
    gap: int = MATCH_GAP,
) -> plt.Axes:
    """Side by side, ``gap`` pixels apart, with inlier matches green and outliers red."""
    canvas, offset = match_canvas(image0, image1, gap)
    axis = axis or plt.subplots(figsize=(10, 4))[1]
    axis.imshow(canvas)
    order = np.argsort(~inlier_mask)[:max_lines]
    for index in order:
        (x0, y0), (x1, y1) = points0[index], points1[index]
        axis.plot([x0, x1 + offset], [y0, y1], color="lime" if inlier_mask[index] else "red", linewidth=0.6, alpha=0.8)
    axis.axis("off")
    return axis


def pair_matches(
    images: tuple[np.ndarray, np.ndarray], view: pd.DataFrame, lines: dict[str, dict[str, np.ndarray]], title: str = ""
) -> plt.Figure:
    """One pair's matches and inliers, one row a method of ``view`` (explore's table), each
    titled with its score and rank; ``lines``: each method's ``verifier_inputs.match_lines``."""
    figure, axes = plt.subplots(len(view), 1, figsize=(10, 3.4 * len(view)), squeeze=False)
    for axis, row in zip(axes[:, 0], view.itertuples()):
        method = str(row.method)
        drawn = lines[method]
        draw_matches(*images, drawn["points0"], drawn["points1"], drawn["inlier_mask"], axis=axis)
        axis.set_title(
            f"{method}: score {row.score} ({row.num_inliers} inliers{collapsed_inliers.inlier_keypoints_words(row)} "
            f"of {row.num_matches} matches), rank {row.rank} of {row.n_pairs}",
            fontsize=9,
        )
    if title:
        figure.suptitle(title)
    figure.tight_layout()
    return figure


def score_histograms(tables: dict[str, pd.DataFrame], view: pd.DataFrame, columns: int = 2) -> plt.Figure:
    """Each method's true and false scores with one pair's score marked (explore's ``view``), at most
    ``columns`` panels a row and one legend."""
    count = len(view)
    ncols = min(columns, count)
    nrows = -(-count // ncols)
    figure, axes = plt.subplots(nrows, ncols, figsize=(5 * ncols, 3 * nrows + 0.6), squeeze=False)
    for axis, row in zip(axes.flat, view.itertuples()):
        table = tables[str(row.method)]
        bins = np.histogram_bin_edges(table["score"], bins=min(40, max(5, table["score"].nunique())))
        for label, colour, name in ((1, "tab:green", "true pairs"), (0, "tab:red", "false pairs")):
            axis.hist(table.loc[table["label"] == label, "score"], bins=bins.tolist(), histtype="step", color=colour,
                      label=name)  # fmt: skip
        axis.axvline(float(row.score), color="black", linewidth=1.5, label="this pair")
        axis.set(xlabel="score (RANSAC inliers)", ylabel="pairs",
                 title=f"{row.method}: this pair ranks {row.rank} of {row.n_pairs}")  # fmt: skip
    for axis in axes.flat[count:]:
        axis.set_visible(False)
    handles, labels = axes.flat[0].get_legend_handles_labels()
    figure.legend(handles, labels, loc="upper center", ncol=len(labels), frameon=False)
    figure.tight_layout(rect=(0, 0, 1, 1 - 0.6 / (3 * nrows + 0.6)))
    return figure


def run_label(method: str, profile: str, sequence: str | None = None) -> str:
    """How a run is named in every table and figure: 'sift-nn (repository profile)', scores
    imported from elsewhere 'my-tool (imported)'; ', on night' when the sequence is given."""
    kind = "imported" if profile == IMPORTED_PROFILE else f"{profile} profile"
    return f"{method} ({kind})" + (f", on {sequence}" if sequence else "")


def method_colours(methods: SequenceType[str]) -> dict[str, tuple]:
    palette = plt.get_cmap("tab10")
    return {m: palette(i % 10) for i, m in enumerate(methods)}
