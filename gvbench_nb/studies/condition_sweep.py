"""Controlled condition study: how AP, MR and aliasing move as one condition strengthens.

The reference drive stays a clear day; the query drive is rendered once per (condition, strength)
with only that condition set, so poses, pairs and labels are the same in every cell. ``out_dir``
holds images/ (route.json, pairs.csv, reference/, query_clear/, query_<condition>_<strength>/),
cells/<profile>/<cell>/ (an output folder each, its runs under runs/), cache/ and sweep.csv (one
row a cell, rewritten atomically after each cell, so an interrupted sweep resumes)."""

from __future__ import annotations

import json
import math
import shutil
from collections.abc import Iterable, Mapping
from collections.abc import Sequence as SequenceType
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import matplotlib.pyplot as plt
import numpy as np
import pandas as pd

from gvbench_nb import GVBenchError
from gvbench_nb import methods as method_registry
from gvbench_nb.data import synthetic
from gvbench_nb.data.sequences import Pair, Sequence
from gvbench_nb.io_utils import atomic_write_csv, atomic_write_json, progress_bar
from gvbench_nb.protocol import registry
from gvbench_nb.protocol.images import read_image
from gvbench_nb.protocol.metrics import evaluate_scores
from gvbench_nb.runner import method_outputs, method_runs

SWEEP_COLUMNS = ["condition", "strength", "method", "profile", "ap", "max_recall", "aliasing_share"]
SWEEP_COLUMNS += ["aliasing_chance", "n_pairs", "n_positives", "n_look_alike"]
DEFAULT_STRENGTHS: tuple[float, ...] = (0.0, 0.25, 0.5, 0.75, 1.0)
REFERENCE_FOLDER = "reference"
CLEAR_FOLDER = "query_clear"
NOT_REACHED = "not reached"


class SweepError(GVBenchError, ValueError):
    """A sweep's inputs are inconsistent (other route in the folder, bad strengths...)."""


@dataclass
class SweepRoute:
    """The rendered route of a sweep: where its images are and which pairs it scores."""

    route: synthetic.Route
    image_root: Path
    pairs: pd.DataFrame  # query_frame, reference_frame, label, look_alike

    def frame_name(self, folder: str, frame: int) -> str:
        return f"{folder}/{frame:0{self.route.name_width}d}.png"

    def sequence(self, condition: str, strength: float) -> Sequence:
        """The cell's pairs: its query folder against the shared reference folder."""
        folder, name = query_folder(condition, strength), f"synthetic-{cell_name(condition, strength)}"
        frames = zip(self.pairs["query_frame"], self.pairs["reference_frame"], self.pairs["label"])
        pairs = [
            Pair(self.frame_name(folder, int(q)), self.frame_name(REFERENCE_FOLDER, int(r)), int(y))
            for q, r, y in frames
        ]
        return Sequence(name, self.image_root, pairs)


def strength_text(strength: float) -> str:
    """Strength as folder names and labels write it (two decimals: 0.25, 1.00)."""
    return f"{float(strength):.2f}"


def query_folder(condition: str, strength: float) -> str:
    """Folder of the query drive under one condition; strength 0 is the shared clear render."""
    if float(strength) == 0.0:
        return CLEAR_FOLDER
    return f"query_{condition}_{strength_text(strength)}"


def cell_name(condition: str, strength: float) -> str:
    """Run folder of a cell; every condition's strength 0 is the one ``clear`` cell."""
    return "clear" if float(strength) == 0.0 else f"{condition}_{strength_text(strength)}"


def prepare_route(
    out_dir: str | Path, seed: int = 0, n_frames: int = 30, image_size: SequenceType[int] = (640, 480)
) -> SweepRoute:
    """Build the route, render the clear reference drive once and write the pair list; a folder
    holding another route is refused (its cached results would not belong to this one)."""
    image_root = Path(out_dir) / "images"
    params = {
        "generator_version": synthetic.GENERATOR_VERSION,
        "seed": int(seed),
        "n_frames": int(n_frames),
        "image_size": [int(image_size[0]), int(image_size[1])],
        "max_distance_m": synthetic.DEFAULT_MAX_DISTANCE_M,
        "max_heading_deg": synthetic.DEFAULT_MAX_HEADING_DEG,
        "look_alike_look_ahead_m": synthetic.LOOK_ALIKE_LOOK_AHEAD_M,
    }
    params_path = image_root / "route.json"
    if params_path.exists():
        recorded = json.loads(params_path.read_text())
        if recorded != params:
            changed = sorted(k for k in set(params) | set(recorded) if params.get(k) != recorded.get(k))
            raise SweepError(
                f"{params_path}: this folder holds a sweep of another route ({', '.join(changed)} differ: "
                f"recorded {[recorded.get(k) for k in changed]}, asked {[params.get(k) for k in changed]}). "
                "Use another out_dir, or delete this one to start afresh."
            )
    if n_frames < 6:
        raise SweepError(f"n_frames={n_frames}: a route needs at least 6 frames to have true and false pairs")
    width, height = image_size  # anything but two numbers fails here, as make_route's unpacking would
    route = synthetic.make_route(seed, n_frames, (width, height))
    atomic_write_json(params_path, params)
    _render_folder(image_root / REFERENCE_FOLDER, route.render_reference, route.name_width)

    pairs_path = image_root / "pairs.csv"
    if pairs_path.exists():
        pairs = pd.read_csv(pairs_path)
    else:
        chosen = synthetic.select_pairs(route.scene, route.query, route.reference, seed)
        look_alike = synthetic.look_alike_labels(route.scene, route.query, route.reference)
        pairs = pd.DataFrame(
            [(q, r, label, int(look_alike[q, r])) for q, r, label in chosen],
            columns=["query_frame", "reference_frame", "label", "look_alike"],
        )
        atomic_write_csv(pairs_path, pairs)
    return SweepRoute(route, image_root, pairs)


def _render_folder(folder: Path, render, name_width: int) -> bool:
    """Render into ``folder`` unless it exists (a temporary folder renamed at the end, so an
    existing one is complete); returns whether it rendered."""
    if folder.is_dir():
        return False
    partial = folder.with_name(f".{folder.name}.partial")
    shutil.rmtree(partial, ignore_errors=True)
    synthetic.write_traversal_images(partial, render(), name_width)
    partial.rename(folder)
    return True


def render_query(sweep_route: SweepRoute, condition: str, strength: float) -> Path:
    """The query drive with only ``condition`` at ``strength`` (cached on disk); returns its folder."""
    registry.check_choice("condition", condition, synthetic.CONDITIONS, error=SweepError)
    folder = sweep_route.image_root / query_folder(condition, strength)
    conditions = {} if float(strength) == 0.0 else {condition: float(strength)}
    _render_folder(folder, lambda: sweep_route.route.render_query(conditions), sweep_route.route.name_width)
    return folder


TOP_FALSE_FRACTION = 0.1


def aliasing_share(
    labels: np.ndarray, scores: np.ndarray, look_alike: np.ndarray, top_fraction: float = TOP_FALSE_FRACTION
) -> float:
    """Fraction of look-alikes among the hardest ``top_fraction`` of the false pairs (at least 1):
    the negatives that limit MR. Ties at the cut share the places left in proportion (the expected
    share under a random tie-break), so row order does not matter; NaN without look-alikes."""
    labels, scores, look_alike = (np.asarray(a).ravel() for a in (labels, scores, look_alike))
    false = labels == 0
    if np.any(look_alike.astype(bool) & ~false):
        raise SweepError("look_alike marks a true pair; look-alike pairs must be false by the pose rule")
    if not 0.0 < top_fraction <= 1.0:
        raise SweepError(f"top_fraction={top_fraction} must be in (0, 1]")
    false_scores = scores[false].astype(np.float64)
    false_alike = look_alike[false].astype(bool)
    if not false_alike.any():
        return float("nan")
    k = max(1, math.ceil(top_fraction * len(false_scores) - 1e-9))
    cut = np.sort(false_scores)[::-1][k - 1]
    above = false_scores > cut
    tied = false_scores == cut
    places_left = k - int(above.sum())
    alike_count = false_alike[above].sum() + places_left * false_alike[tied].mean()
    return float(alike_count / k)


def method_profiles(methods: Iterable[str] | str, profile: str | Mapping[str, str]) -> dict[str, str]:
    """Method -> profile: one profile for all, or a mapping naming each method's."""
    try:
        names = method_registry.expand_methods(methods if isinstance(methods, str) else list(methods))
        if isinstance(profile, str):
            profiles = dict.fromkeys(names, profile)
        else:
            missing = [name for name in names if name not in profile]
            if missing:
                raise SweepError(f"profile mapping {dict(profile)} names no profile for {missing}")
            profiles = {name: profile[name] for name in names}
        for value in set(profiles.values()):
            method_registry.check_profile(value)
    except KeyError as error:
        raise SweepError(str(error)) from None
    if not profiles:
        raise SweepError("name at least one method")
    return profiles


def _validate(conditions: Iterable[str], strengths: Iterable[float]) -> tuple[list[str], list[float]]:
    conditions = list(dict.fromkeys(conditions))
    unknown = [c for c in conditions if c not in synthetic.CONDITIONS]
    if unknown:
        raise SweepError(f"unknown condition(s) {unknown}; known: {', '.join(synthetic.CONDITIONS)}")
    values = sorted({round(float(s), 6) for s in strengths} | {0.0})  # the clear cell anchors every curve
    bad = [s for s in values if not 0.0 <= s <= 1.0]
    if bad:
        raise SweepError(f"strengths {bad} outside [0, 1]")
    if not conditions:
        raise SweepError("name at least one condition")
    return conditions, values


def read_sweep(out_dir: str | Path) -> pd.DataFrame:
    """``sweep.csv`` of a sweep folder (empty table with the columns when there is none)."""
    path = Path(out_dir) / "sweep.csv"
    if not path.is_file():
        return pd.DataFrame(columns=SWEEP_COLUMNS)
    table = pd.read_csv(path)
    missing = [c for c in SWEEP_COLUMNS if c not in table.columns]
    if missing:
        raise SweepError(f"{path}: missing column(s) {missing}; delete it to rerun the sweep")
    return _typed(table[SWEEP_COLUMNS])


def _typed(table: pd.DataFrame) -> pd.DataFrame:
    """Column types independent of where rows came from (a CSV reads 0.0 back as int)."""
    floats = ["strength", "ap", "max_recall", "aliasing_share", "aliasing_chance"]
    integers = ["n_pairs", "n_positives", "n_look_alike"]
    texts = ["condition", "method", "profile"]
    return table.astype(
        {**dict.fromkeys(floats, "float64"), **dict.fromkeys(integers, "int64"), **dict.fromkeys(texts, str)}
    )


def _cell_row(
    sweep_route: SweepRoute, table: pd.DataFrame, condition: str, strength: float, method: str, profile: str, where: str
) -> dict[str, Any]:
    labels, scores = table["label"].to_numpy(), table["score"].to_numpy()
    look_alike = sweep_route.pairs["look_alike"].to_numpy()
    metrics = evaluate_scores(labels, scores, where=where)
    n_false = int((labels == 0).sum())
    chance = float(look_alike.sum() / n_false) if n_false else float("nan")
    values: list[Any] = [condition, float(strength), method, profile, metrics["ap"], metrics["max_recall"]]
    values += [aliasing_share(labels, scores, look_alike), chance, metrics["n_pairs"], metrics["n_positives"]]
    return dict(zip(SWEEP_COLUMNS, [*values, int(look_alike.sum())]))


def run_sweep(
    out_dir: str | Path,
    methods: Iterable[str] | str,
    conditions: Iterable[str] = synthetic.CONDITIONS,
    strengths: Iterable[float] = DEFAULT_STRENGTHS,
    seed: int = 0,
    n_frames: int = 30,
    profile: str | Mapping[str, str] = "paper",
    image_size: SequenceType[int] = (640, 480),
    device: str = "auto",
    threads: int | None = None,
    progress: bool = True,
) -> pd.DataFrame:
    """Run every (condition, strength, method) cell not yet in ``<out_dir>/sweep.csv``; returns the
    requested cells' rows. Strength 0 is one ``clear`` run shared by the conditions (same images);
    ``profile`` is one for every method or a mapping method -> profile."""
    out_dir = Path(out_dir)
    profiles = method_profiles(methods, profile)
    conditions, strengths = _validate(conditions, strengths)
    sweep_route = prepare_route(out_dir, seed, n_frames, image_size)
    rows = read_sweep(out_dir).to_dict("records")
    finished = {(r["condition"], round(float(r["strength"]), 6), r["method"], r["profile"]) for r in rows}

    # One run a query folder: strength 0 is a single clear run whose rows serve every condition.
    cells = [(0.0, conditions)] + [(s, [c]) for c in conditions for s in strengths if s > 0.0]
    bar = progress_bar(total=len(cells) * len(profiles), desc="condition sweep", unit="cell", disable=not progress)
    options: dict[str, Any] = {"device": device, "seed": seed, "progress": progress, "threads": threads}
    for strength, targets in cells:
        for method, method_profile in profiles.items():
            wanted = [c for c in targets if (c, strength, method, method_profile) not in finished]
            if wanted:
                # The cell's query folder rendered (if needed), the method run, one row a condition.
                render_query(sweep_route, wanted[0], strength)
                run_dir = out_dir / "cells" / method_profile / cell_name(wanted[0], strength)
                sequence = sweep_route.sequence(wanted[0], strength)
                scored = method_runs.run_method(sequence, method, method_profile, run_dir, out_dir / "cache", **options)
                where = str(method_outputs.method_dir(run_dir, method) / "pairs.csv")
                rows += [_cell_row(sweep_route, scored, c, strength, method, method_profile, where) for c in wanted]
                finished.update((c, strength, method, method_profile) for c in wanted)
                atomic_write_csv(out_dir / "sweep.csv", _ordered(pd.DataFrame(rows, columns=SWEEP_COLUMNS)))
            bar.update()
    bar.close()
    table = _ordered(pd.DataFrame(rows, columns=SWEEP_COLUMNS))
    profile_asked = np.array([profiles.get(m) == p for m, p in zip(table["method"], table["profile"])], dtype=bool)
    keep = table["condition"].isin(conditions) & table["strength"].round(6).isin(strengths) & profile_asked
    return table[keep].reset_index(drop=True)


def _ordered(table: pd.DataFrame) -> pd.DataFrame:
    order = ["condition", "profile", "method", "strength"]
    return _typed(table).sort_values(order, kind="stable").reset_index(drop=True)


def breaking_strength(sweep: pd.DataFrame) -> pd.DataFrame:
    """Per condition, method and profile: the lowest strength at which MR falls below half its
    clear (strength 0) value, interpolated between grid strengths (NaN with a ``note`` why)."""
    rows = []
    for (condition, method, profile), group in sweep.groupby(["condition", "method", "profile"], sort=False):
        group = group.sort_values("strength")
        strengths = group["strength"].to_numpy(dtype=np.float64)
        recall = group["max_recall"].to_numpy(dtype=np.float64)
        row = dict(zip(BREAKING_COLUMNS, (condition, method, profile, float("nan"), float("nan"), "")))
        if len(strengths) == 0 or strengths[0] != 0.0:
            row["note"] = "no strength-0 (clear) cell"
        elif recall[0] == 0.0:
            row.update(clear_max_recall=0.0, note="undefined: clear MR is 0")
        else:
            row["clear_max_recall"] = float(recall[0])
            row["breaking_strength"], row["note"] = _crossing(strengths, recall, recall[0] / 2.0)
        rows.append(row)
    return pd.DataFrame(rows, columns=BREAKING_COLUMNS)


BREAKING_COLUMNS = ["condition", "method", "profile", "clear_max_recall", "breaking_strength", "note"]


def _crossing(strengths: np.ndarray, values: np.ndarray, level: float) -> tuple[float, str]:
    """First strength where the piecewise-linear curve drops below ``level``."""
    for i in range(1, len(strengths)):
        if values[i] < level:
            fraction = (values[i - 1] - level) / (values[i - 1] - values[i])
            return float(strengths[i - 1] + fraction * (strengths[i] - strengths[i - 1])), ""
    return float("nan"), f"{NOT_REACHED} (up to {strengths[-1]:g})"


def breaking_strength_table(sweep: pd.DataFrame) -> pd.DataFrame:
    """Breaking strengths as a method x condition table of text ('0.43', 'not reached')."""
    table = breaking_strength(sweep)
    table["label"] = [_label(method, profile) for method, profile in zip(table["method"], table["profile"])]
    table["value"] = [
        f"{b:.2f}" if math.isfinite(b) else (note or NOT_REACHED)
        for b, note in zip(table["breaking_strength"], table["note"])
    ]
    return table.pivot(index="label", columns="condition", values="value").rename_axis(index="method", columns=None)


def _label(method: str, profile: str) -> str:
    return method if profile == "paper" else f"{method} ({profile})"


def plot_condition(sweep: pd.DataFrame, condition: str) -> plt.Figure:
    """AP, MR and aliasing share against strength, one line a method (dotted: chance share)."""
    data = sweep[sweep["condition"] == condition].sort_values("strength")
    if data.empty:
        raise SweepError(f"no rows for condition {condition!r} in the sweep table")
    figure, axes = plt.subplots(1, 3, figsize=(13, 3.6), sharex=True)
    for (method, profile), group in data.groupby(["method", "profile"], sort=False):
        label = _label(method, profile)
        for axis, column in zip(axes, ("ap", "max_recall", "aliasing_share")):
            axis.plot(group["strength"], group[column], marker="o", label=label)
    chance = data.groupby("strength")["aliasing_chance"].first()
    axes[2].plot(chance.index, chance.values, linestyle=":", color="grey", label="chance")
    titles = ("AP", "MR (recall at precision 1)", f"look-alike share of the top {TOP_FALSE_FRACTION:.0%} false pairs")
    for axis, title in zip(axes, titles):
        axis.set(xlabel=f"{condition} strength", title=title, ylim=(-0.02, 1.02))
        axis.grid(alpha=0.3)
    axes[0].legend(fontsize=8, loc="lower left")
    axes[2].legend(fontsize=8, loc="best")
    figure.suptitle(f"{condition}: query drive degraded, reference clear ({int(data['n_pairs'].iloc[0])} pairs)")
    figure.tight_layout()
    return figure


def plot_examples(
    out_dir: str | Path, conditions: SequenceType[str], strengths: SequenceType[float], frame: int | None = None
) -> plt.Figure:
    """One query frame under each condition (rows) at each strength (columns), from disk."""
    image_root = Path(out_dir) / "images"
    params = json.loads((image_root / "route.json").read_text())
    width = max(3, len(str(params["n_frames"] - 1)))
    frame = params["n_frames"] // 2 if frame is None else frame
    strengths = sorted({float(s) for s in strengths} | {0.0})
    figure, axes = plt.subplots(
        len(conditions), len(strengths), figsize=(2.6 * len(strengths), 2.1 * len(conditions)), squeeze=False
    )
    for axis_row, condition in zip(axes, conditions):
        for axis, strength in zip(axis_row, strengths):
            path = image_root / query_folder(condition, strength) / f"{frame:0{width}d}.png"
            if not path.is_file():
                raise FileNotFoundError(f"{path} is missing: run the sweep for {condition} at {strength:g} first")
            axis.imshow(read_image(path))
            axis.set_title(f"{condition} {strength:g}", fontsize=9)
            axis.axis("off")
    figure.suptitle(f"query frame {frame} across strengths (reference drive stays clear)")
    figure.tight_layout()
    return figure


def plot_overview(sweep: pd.DataFrame) -> plt.Figure:
    """MR against strength, one panel a condition, one line a method; the dashed mark on
    each line is its breaking strength (MR below half its clear value)."""
    conditions = list(dict.fromkeys(sweep["condition"]))
    breaking = breaking_strength(sweep).set_index(["condition", "method", "profile"])["breaking_strength"]
    figure, axes = plt.subplots(1, len(conditions), figsize=(4.4 * len(conditions), 3.8), sharey=True, squeeze=False)
    for axis, condition in zip(axes[0], conditions):
        data = sweep[sweep["condition"] == condition].sort_values("strength")
        for (method, profile), group in data.groupby(["method", "profile"], sort=False):
            (line,) = axis.plot(group["strength"], group["max_recall"], marker="o", label=_label(method, profile))
            strength = breaking.get((condition, method, profile), float("nan"))
            if math.isfinite(strength):
                axis.axvline(strength, color=line.get_color(), linestyle="--", linewidth=0.8, alpha=0.7)
        axis.set(title=condition, xlabel="strength", ylim=(-0.02, 1.02))
        axis.grid(alpha=0.3)
    axes[0][0].set_ylabel("MR (recall at precision 1)")
    axes[0][-1].legend(fontsize=8, loc="upper right")
    figure.suptitle("MR as one condition strengthens (dashed: breaking strength, MR < half its clear value)")
    figure.tight_layout()
    return figure
