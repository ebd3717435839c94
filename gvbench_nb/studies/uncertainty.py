"""What notebooks/analysis_uncertainty.ipynb draws: AP and MR with their 95 % bootstrap intervals over
queries (``evaluation/bootstrap.py`` computes them).
"""

from __future__ import annotations

import matplotlib.pyplot as plt
import numpy as np
import pandas as pd

from gvbench_nb.evaluation import run_tables


def bootstrap_intervals(intervals: pd.DataFrame, title: str = "", labels: dict[str, str] | None = None) -> plt.Figure:
    """Point estimate and 95% percentile CI of AP and MR in %, one row a method (named by ``labels``
    where it has one, ``run_tables.run_labels``)."""
    metrics = list(dict.fromkeys(intervals["metric"]))
    size = (5 * len(metrics), 0.45 * intervals["method"].nunique() + 1.8)
    figure, axes = plt.subplots(1, len(metrics), figsize=size, squeeze=False, sharey=True)
    for axis, metric in zip(axes[0], metrics):
        data = intervals[intervals["metric"] == metric].reset_index(drop=True)
        data[["estimate", "low", "high"]] *= 100  # in %, as AP and MR are everywhere
        y = np.arange(len(data))
        errors = np.vstack([data["estimate"] - data["low"], data["high"] - data["estimate"]])
        axis.errorbar(data["estimate"], y, xerr=np.clip(errors, 0, None), fmt="o", capsize=4, color="tab:blue")
        for i, row in data.iterrows():
            text = f"  {row['estimate']:.1f} [{row['low']:.1f}, {row['high']:.1f}]"
            axis.text(row["high"], i, text, va="center", fontsize=7)
        axis.set_yticks(y, data["method"].replace(labels or {}))
        axis.set_xticks(np.linspace(0, 100, 6))
        header = run_tables.METRIC_HEADERS.get(metric, metric)
        axis.set(xlabel=f"{header}, 95% CI (queries resampled)", xlim=(0, 135))
        axis.grid(alpha=0.3, axis="x")
    axes[0, 0].invert_yaxis()  # once: the axes share y, so a second call would undo it
    if title:
        figure.suptitle(title)
    figure.tight_layout()
    return figure
