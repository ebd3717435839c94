"""What notebooks/analysis_inlier_histograms.ipynb computes and draws: inlier counts of true vs false pairs."""

from __future__ import annotations

import matplotlib.pyplot as plt
import numpy as np
import pandas as pd

from gvbench_nb.evaluation import plots


# ------------------------------------------------------------------- inliers --
def normalised_inliers(table: pd.DataFrame) -> pd.Series:
    """Inliers / the method's largest inlier count (the paper's normalisation; 0 when all are 0)."""
    largest = table["num_inliers"].max()
    return table["num_inliers"] / largest if largest > 0 else table["num_inliers"] * 0.0


def inlier_overlap_summary(table: pd.DataFrame) -> dict[str, float]:
    """What caps MR: the top false pair's score and the share of true pairs strictly above it
    (``true_above_top_false``, i.e. MR)."""
    true_scores = table.loc[table["label"] == 1, "score"].to_numpy(dtype=float)
    false_scores = table.loc[table["label"] == 0, "score"].to_numpy(dtype=float)
    if len(true_scores) == 0 or len(false_scores) == 0:
        raise ValueError("need both true and false pairs to describe their overlap")
    top_false = float(false_scores.max())
    largest = float(table["score"].max()) or 1.0
    return {
        "n_true": int(len(true_scores)),
        "n_false": int(len(false_scores)),
        "true_zero_inliers": float(np.mean(true_scores == 0)),
        "false_zero_inliers": float(np.mean(false_scores == 0)),
        "top_false_score": top_false,
        "top_false_normalised": top_false / largest,
        "true_above_top_false": float(np.mean(true_scores > top_false)),
        "true_in_overlap": float(np.mean(true_scores <= top_false)),
    }


def with_inlier_counts(tables: dict[str, pd.DataFrame]) -> tuple[dict[str, pd.DataFrame], list[str]]:
    """The tables holding inlier counts, and one line naming each that holds none (scores imported
    from a table of scores alone): nothing to draw there."""
    counted = {m: t for m, t in tables.items() if t["num_inliers"].notna().any()}
    lines = [
        f"{plots.run_label(m, str(t['profile'].iloc[0]))}: its scores come without inlier counts; no panel"
        for m, t in tables.items()
        if m not in counted
    ]
    return counted, lines


def inlier_overlap_table(tables: dict[str, pd.DataFrame]) -> pd.DataFrame:
    return pd.DataFrame([{"method": m, **inlier_overlap_summary(t)} for m, t in tables.items()])


def normalised_inlier_histograms(tables: dict[str, pd.DataFrame], title: str = "", bins: int = 30) -> plt.Figure:
    """Normalised inlier counts of true vs false pairs, a panel a run (Figs. 6, 8, 9); shaded above the
    top false score, annotated with the share of true pairs at zero inliers."""
    n = len(tables)
    columns = min(n, 3)
    rows = int(np.ceil(n / columns))
    figure, axes = plt.subplots(rows, columns, figsize=(4.6 * columns, 3.2 * rows), squeeze=False)
    edges = np.linspace(0, 1, bins + 1)
    for axis, (method, table) in zip(axes.ravel(), tables.items()):
        normalised = normalised_inliers(table)
        summary = inlier_overlap_summary(table)
        for label, name, colour in ((1, "true", "tab:green"), (0, "false", "tab:red")):
            chosen = table["label"] == label
            shown = {"color": colour, "alpha": 0.55, "label": f"{name} ({int(chosen.sum())})", "density": True}
            axis.hist(normalised[chosen], bins=edges, **shown)
        top = summary["top_false_normalised"]
        axis.axvspan(top, 1.0, color="tab:blue", alpha=0.08)
        axis.axvline(top, color="tab:blue", linestyle="--", linewidth=1)
        note = (
            f"true pairs above top false: {summary['true_above_top_false']:.1%} (= MR)\n"
            f"true pairs with 0 inliers: {summary['true_zero_inliers']:.1%}"
        )
        box = {"facecolor": "white", "alpha": 0.8, "edgecolor": "none"}
        axis.text(0.98, 0.95, note, transform=axis.transAxes, ha="right", va="top", fontsize=7, bbox=box)
        profiles = table["profile"].unique() if "profile" in table else []
        if len(profiles) > 1:
            raise ValueError(
                f"the pairs table of {method!r} mixes profiles {sorted(profiles)}; "
                "give each profile's table its own key"
            )
        panel = plots.run_label(method, profiles[0]) if len(profiles) else method
        axis.set(title=panel, xlabel="inliers / method's max inliers", ylabel="density")
        axis.legend(fontsize=7, loc="center right")
    for axis in axes.ravel()[n:]:
        axis.axis("off")
    if title:
        figure.suptitle(title)
    figure.tight_layout()
    return figure
