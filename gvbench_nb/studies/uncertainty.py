"""What notebooks/analysis_uncertainty.ipynb draws: AP and MR with their 95 % bootstrap intervals over
queries (``evaluation/bootstrap.py`` computes them).
"""

from __future__ import annotations

import matplotlib.pyplot as plt
import numpy as np
import pandas as pd


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
