"""What notebooks/analysis_deployment.ipynb and ``transfer`` compute: each method's oracle threshold of a
calibration sequence applied to other sequences (precision, recall, false loops), and recall@1 per query."""

from __future__ import annotations

import argparse
import logging
import os
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from gvbench_nb.evaluation import run_tables

RETRIEVAL_BUILDER = "retrieval"  # the pairs builder whose pair files keep the retrieval order
NOT_ALL_DONE = 3  # transfer's exit status when it printed what it could and names on stderr what it could not do
log = logging.getLogger(__name__)


def oracle_threshold(labels: np.ndarray, scores: np.ndarray) -> float:
    """The smallest score above every false pair's score (infinity when none): the threshold MR is read
    at, since precision is 1 exactly above every false score."""
    labels = np.asarray(labels).astype(bool)
    scores = np.asarray(scores, dtype=np.float64)
    highest_false = scores[~labels].max() if (~labels).any() else -np.inf
    above = scores[scores > highest_false]
    return float(above.min()) if len(above) else float("inf")


def apply_threshold(labels: np.ndarray, scores: np.ndarray, threshold: float) -> dict[str, float]:
    """Pairs accepted at ``score >= threshold``: precision (NaN when none is), recall, false loops."""
    labels = np.asarray(labels).astype(bool)
    accepted = np.asarray(scores, dtype=np.float64) >= threshold
    true_accepted = int((accepted & labels).sum())
    false_accepted = int((accepted & ~labels).sum())
    n_accepted = true_accepted + false_accepted
    return {
        "precision": true_accepted / n_accepted if n_accepted else float("nan"),
        "recall": true_accepted / int(labels.sum()) if labels.any() else float("nan"),
        "false_loops": false_accepted,
        "n_accepted": n_accepted,
    }


class DeploymentInputs:
    """Every folder's pairs tables by sequence, read through the readers ``results`` shares:
    ``run_tables.load_results`` refuses a folder whose results are not a finished run's,
    edited since or computed from inputs that changed."""

    def __init__(self, output_dirs: Iterable[str | os.PathLike[str]]):
        folders = [Path(f) for f in output_dirs]
        self.results = run_tables.load_results(folders)
        # sequence -> method -> profile -> its pairs table: a folder labels a row by what tells its own
        # rows apart (``orb-nn (paper profile)``), which another folder need not share
        self.tables: dict[str, dict[str, dict[str, pd.DataFrame]]] = {}
        self.keeps_retrieval_order: dict[str, bool] = {}
        for folder in folders:
            rows = self.results[self.results["output_dir"] == str(folder)]
            sequence = str(rows["sequence"].iloc[0])
            if sequence in self.tables:
                raise run_tables.IncomparableRunsError(
                    f"{folder}: sequence {sequence!r} is given twice; pass one output folder a sequence"
                )
            methods = list(rows["method"])
            tables = run_tables.load_pairs_tables(folder, methods)
            base = rows["method"].str.split(" (", n=1, regex=False).str[0]
            twice = pd.Series(list(zip(base, rows["profile"])), index=rows.index).duplicated(keep=False)
            self.tables[sequence] = {}
            for label, method, profile in zip(methods, base.where(~twice, rows["method"]), rows["profile"]):
                self.tables[sequence].setdefault(method, {})[profile] = tables[label]
            builder = (run_tables.load_run(folder, methods[0]).get("pairs") or {}).get("pairs_builder")
            self.keeps_retrieval_order[sequence] = builder == RETRIEVAL_BUILDER

    @property
    def sequences(self) -> list[str]:
        return list(self.tables)

    def methods(self) -> list[str]:
        return list(dict.fromkeys(m for tables in self.tables.values() for m in tables))


def transfer_table(inputs: DeploymentInputs, calibrations: Iterable[str] | None = None) -> pd.DataFrame:
    """One row a (method, calibration sequence, target sequence): the calibration's oracle
    threshold and what it accepts on the target. The diagonal is MR itself. A threshold goes
    only to a run of the same method under the same profile."""
    calibrations = list(calibrations or inputs.sequences)
    unknown = [c for c in calibrations if c not in inputs.tables]
    if unknown:
        raise run_tables.IncomparableRunsError(
            f"calibration sequence(s) {', '.join(unknown)} not among the folders read "
            f"({', '.join(inputs.sequences)}); name one of those, or add its output folder"
        )
    rows = []
    for method in inputs.methods():
        for calibration in calibrations:
            for profile, source in inputs.tables[calibration].get(method, {}).items():
                threshold = oracle_threshold(source["label"], source["score"])
                for target, tables in inputs.tables.items():
                    if profile in tables.get(method, {}):
                        target_table = tables[method][profile]
                        applied = apply_threshold(target_table["label"], target_table["score"], threshold)
                        rows.append({"method": method, "profile": profile, "calibration": calibration,
                                     "target": target, "threshold": threshold, **applied})  # fmt: skip
    return pd.DataFrame(rows)


def not_transferred(inputs: DeploymentInputs, calibrations: Iterable[str], table: pd.DataFrame) -> list[str]:
    """What ``transfer_table`` could not do, one line each, and why: a method without results on a
    calibration sequence (no threshold), a target without the method or holding it under another
    profile, and each target left out altogether."""
    lines = []
    for calibration in calibrations:
        for method in inputs.methods():
            if method not in inputs.tables[calibration]:
                lines.append(f"{method}: no threshold, calibration sequence {calibration} has no results of it")
                continue
            for profile in inputs.tables[calibration][method]:
                for target in inputs.sequences:
                    held = list(inputs.tables[target].get(method, {}))
                    if profile not in held:
                        why = (
                            f"holds it under the {' and '.join(held)} profile (a threshold goes only to a run of "
                            "the same profile)"
                            if held
                            else "has no results of it"
                        )
                        lines.append(
                            f"{method} ({profile} profile, calibrated on {calibration}): not transferred to "
                            f"{target}, which {why}"
                        )
    done = set(table["target"]) if len(table) else set()
    lines += [f"target {t} left out: no method could take a threshold there" for t in inputs.sequences if t not in done]
    return lines


def runs(table: pd.DataFrame) -> list[tuple[str, str]]:
    """The (method, profile) of a transfer table, in order: one matrix each."""
    return list(dict.fromkeys(zip(table["method"], table["profile"])))


def transfer_matrix(table: pd.DataFrame, method: str, profile: str) -> pd.DataFrame:
    """One run's matrix, calibration rows by target columns: 'precision / recall / false loops'."""
    rows = table[(table["method"] == method) & (table["profile"] == profile)]
    cells = [
        f"{'-' if np.isnan(r.precision) else f'{r.precision:.3f}'} / {r.recall:.3f} / {r.false_loops}"
        for r in rows.itertuples()
    ]
    matrix = rows.assign(cell=cells).pivot(index="calibration", columns="target", values="cell")
    order = list(dict.fromkeys(rows["calibration"]))
    thresholds = rows.drop_duplicates("calibration").set_index("calibration")["threshold"]
    matrix = matrix.loc[order, list(dict.fromkeys(rows["target"]))]
    matrix.index = [f"{c} (threshold {thresholds[c]:g})" for c in order]
    matrix.index.name, matrix.columns.name = "calibration", "target"
    return matrix


def query_outcomes(table: pd.DataFrame, threshold: float) -> pd.DataFrame:
    """One row a query: is its first candidate (file order) true, is its best-scoring one true
    (ties keep file order), and does the best one pass ``threshold``."""
    ordered = table.sort_values("pair_index", kind="stable") if "pair_index" in table else table
    grouped = ordered.groupby("query", sort=False)
    first = grouped["label"].first().astype(bool)
    best = ordered.loc[grouped["score"].idxmax()].set_index("query")
    return pd.DataFrame(
        {
            "has_true": grouped["label"].max().astype(bool),
            "first_true": first,
            "best_true": best["label"].astype(bool),
            "best_passes": best["score"] >= threshold,
        }
    )


def loop_closure_table(transfer: pd.DataFrame, inputs: DeploymentInputs) -> pd.DataFrame:
    """Per (method, calibration, target): recall@1 after GV re-ranking and before it (where the
    pair file keeps the retrieval order), over the queries with a true candidate, and the queries
    whose best candidate passes the transferred threshold, a true or a false loop."""
    rows = []
    for row in transfer.itertuples():
        outcomes = query_outcomes(inputs.tables[row.target][row.method][row.profile], row.threshold)
        findable = outcomes[outcomes["has_true"]]
        closed = outcomes[outcomes["best_passes"]]
        kept = inputs.keeps_retrieval_order[row.target]
        recall_gv = findable["best_true"].mean() if len(findable) else float("nan")
        recall_retrieval = findable["first_true"].mean() if kept and len(findable) else float("nan")
        counts = (len(outcomes), len(findable), recall_gv, recall_retrieval)
        closures = (int(closed["best_true"].sum()), int((~closed["best_true"]).sum()))
        rows.append((row.method, row.profile, row.calibration, row.target, *counts, *closures))
    return pd.DataFrame(rows, columns=LOOP_COLUMNS)


LOOP_COLUMNS = ["method", "profile", "calibration", "target", "n_queries", "queries_with_true", "recall_at_1_gv"]
LOOP_COLUMNS += ["recall_at_1_retrieval", "true_loops_closed", "false_loops_closed"]
LOOP_SHARES = ["recall_at_1_gv", "recall_at_1_retrieval"]  # shown in %, as AP and MR


def transfer_text(inputs: DeploymentInputs, calibrations: list[str], table: pd.DataFrame | None = None) -> str:
    """What ``transfer`` prints: a matrix a method, then the loop-closure table."""
    from gvbench_nb.evaluation.plots import run_label

    table = transfer_table(inputs, calibrations) if table is None else table
    parts = [
        "Each method's threshold of 100% precision on the calibration sequence (the one MR is read at), "
        "applied to each target: precision / recall / false loops accepted ('-': nothing accepted).\n"
    ]
    for method, profile in runs(table):
        parts.append(f"{run_label(method, profile)}\n{transfer_matrix(table, method, profile).to_string()}\n")
    loops = loop_closure_table(table, inputs)
    parts.append(
        "Loop closures: each query keeps its best-scoring candidate. recall_at_1_gv: its share of the queries "
        "with a true candidate whose best is true; recall_at_1_retrieval: the same for the first candidate, "
        "where the pair file keeps the retrieval order (NaN: it does not); *_loops_closed: queries whose best "
        "candidate passes the calibration's threshold.\n"
    )
    parts.append(loops.to_string(index=False, float_format=lambda v: f"{v:.3f}"))
    return "\n".join(parts)


def transfer_figure(table: pd.DataFrame) -> Any:
    """Recall of every transfer, a panel a (method, profile) (calibration rows, target columns), each cell
    annotated with its false loops; the diagonal is MR."""
    import matplotlib.pyplot as plt

    from gvbench_nb.evaluation import plots

    panels = runs(table)
    # A panel's side grows with its sequences and the panels wrap three a row, so a cell's text
    # keeps its size on the page whether the matrix is 1x1 or 6x6.
    size = table["calibration"].nunique()
    side, columns = max(3.2, 1.0 * size + 1.6), min(3, len(panels))
    rows = -(-len(panels) // columns)
    figure, axes = plt.subplots(
        rows, columns, figsize=(side * columns + 1.5, side * rows + 0.8), squeeze=False, layout="constrained"
    )
    for number, (axis, (method, profile)) in enumerate(zip(axes.flat, panels)):
        cells = table[(table["method"] == method) & (table["profile"] == profile)]
        recall = cells.pivot(index="calibration", columns="target", values="recall")
        false_loops = cells.pivot(index="calibration", columns="target", values="false_loops")
        image = axis.imshow(100 * recall.to_numpy(dtype=float), vmin=0, vmax=100, cmap="viridis")
        for (i, j), value in np.ndenumerate(100 * recall.to_numpy(dtype=float)):
            text = f"R {value:.1f}%\n{int(false_loops.iat[i, j])} false"
            axis.text(j, i, text, ha="center", va="center", fontsize=9, color="white" if value < 60 else "black")
        axis.set_xticks(range(recall.shape[1]), recall.columns, rotation=30, ha="right", fontsize=9)
        axis.set_yticks(range(recall.shape[0]), recall.index, fontsize=9)
        axis.set(
            xlabel="deployed on (target)", ylabel="threshold fixed on (calibration)" if number % columns == 0 else ""
        )
        axis.set_title(plots.run_label(method, profile), fontsize=10)
    for axis in axes.flat[len(panels) :]:
        axis.set_visible(False)
    figure.colorbar(image, ax=axes.ravel().tolist(), shrink=0.8, label="recall at the transferred threshold (%)")
    figure.suptitle("Threshold transfer: recall and false loops accepted (diagonal: MR)", fontsize=10)
    return figure


def command_transfer(args: argparse.Namespace) -> int:
    folders = [args.calibration_dir, *args.target_dirs]
    inputs = DeploymentInputs(folders)
    calibrations = inputs.sequences if args.every else inputs.sequences[:1]
    table = transfer_table(inputs, calibrations)
    missing = not_transferred(inputs, calibrations, table)
    if not len(table):
        raise run_tables.IncomparableRunsError(
            f"nothing to transfer: {'; '.join(missing)}; give output folders holding runs of one method and profile"
        )
    print(transfer_text(inputs, calibrations, table))
    for line in missing:
        log.warning(f"not done: {line}")
    return NOT_ALL_DONE if missing else 0


def add_command(subparsers: argparse._SubParsersAction) -> None:
    """Register ``transfer CALIBRATION_DIR TARGET_DIR [...]``."""
    parser = subparsers.add_parser(
        "transfer",
        help="fix each method's 100%%-precision threshold on one sequence and apply it to others",
        description="For each method, the inlier threshold that gives 100% precision on the calibration "
        "folder's sequence (the one MR is read at) applied to each target folder: precision, recall and "
        "false loops accepted, as a matrix over sequences; then, per query, recall@1 after GV re-ranking "
        "and the queries that would close a false loop. Reads only finished runs. Names on stderr each method "
        "and target it could not transfer, and why, and then exits with status 3.",
    )
    parser.add_argument("calibration_dir", help="output folder of the sequence the thresholds are fixed on")
    parser.add_argument("target_dirs", nargs="+", metavar="target_dir", help="output folders to deploy on")
    parser.add_argument("--every", action="store_true", help="calibrate on every folder given, not only the first")
    parser.set_defaults(handler=command_transfer)
