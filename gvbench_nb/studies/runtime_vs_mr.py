"""What notebooks/analysis_runtime_vs_mr.ipynb computes and draws: seconds a pair by stage, speed against MR."""

from __future__ import annotations

import os
from collections.abc import Sequence as SequenceType
from pathlib import Path
from typing import Any

import matplotlib.pyplot as plt
import numpy as np
import pandas as pd
from matplotlib.ticker import FuncFormatter, LogLocator, NullFormatter

from gvbench_nb.evaluation import plots, run_tables
from gvbench_nb.runner import image_features, scoring


# --------------------------------------------------------------------- runtime --
def runtime_table(results: pd.DataFrame) -> pd.DataFrame:
    """Seconds per pair split by stage (extraction amortised over the pairs using an
    image), total, FPS = 1 / seconds per pair, and MR - one row a (sequence, method)."""
    measured = results[results["seconds_per_pair"].notna()]  # imported scores: no seconds were measured here
    table = measured[
        ["sequence", "method", "profile", "device", *run_tables.TIME_COLUMNS, "seconds_per_pair", "max_recall", "ap"]
    ].copy()
    table["fps"] = 1.0 / table["seconds_per_pair"]
    return table


def unmeasured_lines(results: pd.DataFrame) -> list[str]:
    """One line for each run without seconds (scores imported from elsewhere): left out below."""
    absent = results[results["seconds_per_pair"].isna()]
    return [
        f"{plots.run_label(m, p, s)}: no seconds were measured here (scores imported); not in the runtime views"
        for m, p, s in zip(absent["method"], absent["profile"], absent["sequence"])
    ]


def traversal_sizes(
    output_dir: str | os.PathLike[str], method: str, run: dict[str, Any], cache_dir: Path
) -> dict[str, tuple[int, int] | None]:
    """Original (width, height) of each traversal (an image folder of the queries or references; a
    query folder first), read from its first image; None where that image cannot be read."""
    pairs = scoring.load_pairs_table(Path(output_dir), method)
    firsts: dict[str, str] = {}
    for name in [*pairs["query"], *pairs["reference"]]:
        firsts.setdefault(name.rsplit("/", 1)[0] if "/" in name else ".", name)
    return {folder: image_size(name, run, cache_dir) for folder, name in firsts.items()}


def image_size(name: str, run: dict[str, Any], cache_dir: Path) -> tuple[int, int] | None:
    """Original (width, height) of one image of a run: from the feature cache, else (dense
    matchers, or no cache here) the image file's header; None when neither is there."""
    extractor = run["conf"].get("extractor")
    if extractor:
        store = image_features.feature_store(cache_dir, extractor)
        try:
            key: str | None = image_features.image_key(Path(run["image_root"]), name)
        except OSError:  # the image is gone: no key to look up
            key = None
        if key is not None and store.folder.is_dir() and key in store:
            size = store.read(key)["image_size"]
            store.close()
            return int(size[0]), int(size[1])
    path = Path(run["image_root"]) / name
    if path.is_file():
        from PIL import Image

        with Image.open(path) as image:
            return image.size
    return None


def run_description(
    output_dir: str | os.PathLike[str], methods: SequenceType[str], cache_dir: str | os.PathLike[str] | None = None
) -> str:
    """One line naming device, profile and image sizes of the runs, for figure captions."""
    devices, profiles, sizes = set(), set(), set()
    for method in methods:
        run = run_tables.load_run(output_dir, method)
        environment = run["environment"]
        on_cpu = environment["device"] == "cpu" and "cpu_count" in environment
        cores = f", {environment['cpu_count']} cores" if on_cpu else ""
        devices.add(f"{environment['device']} ({environment.get('device_name') or '?'}{cores})")
        profiles.add(run["conf"]["profile"])
        # Dense matchers (no extractor) resize inside the matcher conf.
        resizing = run["conf"].get("extractor") or run["conf"]["matcher"]
        if resizing is None:  # imported scores: no image was read here
            continue
        resize = resizing.get("resize_max")
        sizes_of = traversal_sizes(output_dir, method, run, run_tables.resolve_cache_dir(output_dir, cache_dir, method))
        native = ", ".join(f"{folder} {f'{s[0]}x{s[1]}' if s else '?'}" for folder, s in sizes_of.items())
        longest = f"{'=' if resizing.get('resize_force') else '<='}{resize}" if resize else "native"
        fixed = resizing.get("resize_to")
        resized = f"resized to {fixed[0]}x{fixed[1]}" if fixed else f"longest side {longest}"
        sizes.add(f"{resizing['name']}: {native}; {resized}")
    return (
        f"device {' / '.join(sorted(devices))}; profile {' / '.join(sorted(profiles))}; "
        f"images {'; '.join(sorted(sizes))}"
    )


STAGE_LABELS = {
    "extract_seconds_per_pair": "extraction (amortised)",
    "match_seconds_per_pair": "matching",
    "verify_seconds_per_pair": "verification (RANSAC)",
}


def seconds_per_pair_stacked(runtime: pd.DataFrame, caption: str = "") -> plt.Figure:
    """Seconds per pair by stage, stacked, one bar a (sequence, profile, method)."""
    several = runtime["sequence"].nunique() > 1
    labels = [
        plots.run_label(m, p, s if several else None)
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
    colours = plots.method_colours(list(dict.fromkeys(runtime["method"])))
    markers = dict(zip(dict.fromkeys(runtime["sequence"]), "osD^vP*X"))
    for row in runtime.itertuples():
        point = (row.fps, 100 * row.max_recall)
        style = {"color": colours[row.method], "marker": markers[row.sequence], "edgecolor": "black"}
        axis.scatter(*point, s=60, linewidth=0.5, **style)
        label = plots.run_label(row.method, row.profile, row.sequence if runtime["sequence"].nunique() > 1 else None)
        axis.annotate(label, point, textcoords="offset points", xytext=(5, 4), fontsize=8)
    axis.set_xscale("log")
    # At least a decade shown, so a log axis keeps readable ticks.
    low, high = float(runtime["fps"].min()), float(runtime["fps"].max())
    middle = np.sqrt(low * high)
    span = max(np.sqrt(high / low) * 1.5, np.sqrt(10))
    axis.set_xlim(middle / span, middle * span)
    # Ticks at 1, 2 and 5 of every decade, written as plain numbers: at least three on the axis.
    axis.xaxis.set_major_locator(LogLocator(subs=(1.0, 2.0, 5.0)))
    axis.xaxis.set_major_formatter(FuncFormatter(lambda value, _: f"{value:g}"))
    axis.xaxis.set_minor_formatter(NullFormatter())
    axis.set(
        xlabel="FPS (pairs a second, 1 / seconds per pair; log scale)",
        ylabel=f"max recall at 100% precision, {run_tables.METRIC_HEADERS['max_recall']}",
        ylim=(-2, max(10.0, 120 * float(runtime["max_recall"].max()))),
    )
    axis.grid(alpha=0.3, which="both")
    axis.set_title("speed vs max recall", fontsize=11)
    figure.tight_layout()
    if caption:
        figure.text(0.01, 0.0, caption, fontsize=7, va="top", wrap=True)
    return figure
