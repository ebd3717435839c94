"""Reading written runs (their tables and records, match stores, feature cache), never recomputing.
``ap`` and ``max_recall`` are fractions everywhere; rows are keyed by (sequence, profile, method)."""

from __future__ import annotations

import os
from collections.abc import Iterable
from collections.abc import Sequence as SequenceType
from pathlib import Path

import pandas as pd
import yaml

from gvbench_nb.data import fetch
from gvbench_nb.data.sequences import name_problem
from gvbench_nb.data.synthetic.route_files import GENERATOR_FILE
from gvbench_nb.evaluation import reference_values
from gvbench_nb.runner import config, method_outputs, runs, scoring
from gvbench_nb.runner.score_files import IMPORTED_PROFILE

METRICS = ("ap", "max_recall")


PAPER_LABEL = reference_values.PAPER_LABEL  # how the paper's numbers are named in every table and figure


REPOSITORY_LABEL = reference_values.REPOSITORY_LABEL  # and the GV-Bench repository's


OURS_LABEL = "ours"


RUN_KEY = ["sequence", "profile", "method"]  # what identifies a run in every table and figure


TIME_COLUMNS = ("extract_seconds_per_pair", "match_seconds_per_pair", "verify_seconds_per_pair")


# AP and MR are shown in % everywhere (as the paper's tables), under these names.
METRIC_HEADERS = {"ap": "AP (%)", "max_recall": "MR (%)"}


# Table headers in words; a column not named here has its underscores read as spaces.
HEADERS = {
    **{f"{m}_{end}": f"{name} {end}" for m, name in (("ap", "AP"), ("max_recall", "MR")) for end in ("low", "high")},
    "ap": "AP",
    "max_recall": "MR",
    "paper_name": "paper's name",
    "n_pairs": "pairs",
    "n_positives": "true pairs",
    "n_true": "true pairs",
    "n_false": "false pairs",
    "n_valid": "resamples with a true pair",
    "n_queries": "queries",
    "fps": "FPS",
    "seconds_per_pair": "seconds a pair",
    "extract_seconds_per_pair": "extraction (s a pair)",
    "match_seconds_per_pair": "matching (s a pair)",
    "verify_seconds_per_pair": "verification (s a pair)",
    "true_zero_inliers": "true pairs with 0 inliers",
    "false_zero_inliers": "false pairs with 0 inliers",
    "top_false_score": "top false score",
    "top_false_normalised": "top false score / largest",
    "true_above_top_false": "true pairs above the top false (MR)",
    "true_in_overlap": "true pairs at or below the top false",
    "recall_at_1_gv": "recall@1 after GV",
    "recall_at_1_retrieval": "recall@1 of retrieval",
    "top_k": "top k",
    "pair_index": "pair",
}


def run_labels(results: pd.DataFrame) -> dict[str, str]:
    """Each method of ``results`` as tables name it: an imported one 'my-tool (imported)'."""
    from gvbench_nb.evaluation import plots

    return {m: plots.run_label(m, p) for m, p in zip(results["method"], results["profile"]) if p == IMPORTED_PROFILE}


def readable_table(
    frame: pd.DataFrame, percent: Iterable[str] = (), labels: dict[str, str] | None = None
) -> pd.DataFrame:
    """``frame`` as a page shows it: AP and MR columns (and ``percent``, other shares) times 100 and
    marked (%), every header in words, a metric named in a cell as in a header ('AP'), the methods
    in ``labels`` by their label there (``run_labels``)."""
    metric_columns = {f"{metric}{end}" for metric in METRICS for end in ("", "_low", "_high")}
    shares = [c for c in frame.columns if c in metric_columns or c in set(percent)]
    shown = frame.assign(**{c: 100 * frame[c] for c in shares})
    for column in ("method", "first", "second"):
        if labels and column in shown:
            shown[column] = shown[column].replace(labels)
    if "metric" in shown and shown["metric"].isin(METRICS).all():
        shown["metric"] = shown["metric"].map({"ap": "AP", "max_recall": "MR"})
    words = {c: HEADERS.get(c, str(c).replace("_", " ")) + (" (%)" if c in shares else "") for c in frame.columns}
    return shown.rename(columns=words)


# ------------------------------------------------------------ finding results --
def find_output_dirs(
    root: str | os.PathLike[str] = config.PROJECT_ROOT / "outputs", sequences: SequenceType[str] | None = None
) -> list[Path]:
    """Output folders under ``root`` showing finished runs (sorted), or exactly those of ``sequences``."""
    root = Path(root)
    if sequences:
        folders = [root / name for name in sequences]
        absent = [str(f) for f in folders if not shows_results(f)]
        if absent:
            raise method_outputs.ResultsError(
                f"no finished run in {', '.join(absent)}; run them first (python -m gvbench_nb run params/NAME.yaml)"
            )
        return folders
    candidates = {p.parent for name in (runs.RUNS, runs.OLD_RECORD) for p in root.glob(f"*/{name}")}
    return sorted(filter(shows_results, candidates))


def shows_results(folder: Path) -> bool:
    """Whether an output folder shows finished runs, or holds results of the earlier layout (which
    its readers refuse in one sentence naming ``upgrade``)."""
    return (folder / runs.OLD_RECORD).is_file() or bool(scoring.methods_with_results(folder))


def load_results(output_dirs: Iterable[str | os.PathLike[str]]) -> pd.DataFrame:
    """The results of several output folders, derived from their runs, one table, plus an ``output_dir`` column,
    ``limit``: the run's ``--limit`` (first N pairs of the pair file; None: every pair), and
    ``synthetic``: whether the folder's images are a route the package rendered."""
    frames = []
    for folder in output_dirs:
        # Derived from the runs the folder shows, from inputs unchanged since, on one set of pairs.
        frame = scoring.evaluate(Path(folder), scoring.readable_methods(folder), write=False)
        for sequence in map(str, frame["sequence"].unique()):  # figures and pages are named by it
            if name_problem(sequence):
                raise method_outputs.ResultsError(
                    f"{folder}: its sequence {sequence!r} {name_problem(sequence)}, so it cannot name figures; "
                    "run its methods again with a plain sequence name"
                )
        records = [load_run(folder, m) for m in frame["method"]]
        limits = [(run.get("pairs") or {}).get("limit") for run in records]
        # An imported method read no images (image_root ''): the folder's other runs tell.
        rendered = any((Path(r["image_root"]) / GENERATOR_FILE).is_file() for r in records if r.get("image_root"))
        limit = pd.Series(limits, dtype=object)
        frames.append(frame.assign(output_dir=str(Path(folder)), limit=limit, synthetic=rendered))
    if not frames:
        raise ValueError("no output folders given: pass at least one output folder of finished runs")
    results = pd.concat(frames, ignore_index=True)
    if "fps" not in results:
        results["fps"] = 1.0 / results["seconds_per_pair"]
    return results


load_run = method_outputs.read_run_json  # a method's record, read by ``runs``


def method_folders(output_dirs: SequenceType[str | os.PathLike[str]]) -> dict[str, Path]:
    """Which of ``output_dirs`` holds each method's finished results; a method in two is refused."""
    found: dict[str, Path] = {}
    for folder in map(Path, output_dirs):
        ran = scoring.methods_with_results(folder)
        if not ran:
            scoring.evaluate(folder, write=False)  # says the folder does not exist or holds no results
        for method in ran:
            if method in found:
                raise IncomparableRunsError(
                    f"method {method!r} has results in both {found[method]} and {folder}; "
                    "pass only one of the two folders"
                )
            found[method] = folder
    return found


def load_pairs_tables(
    output_dirs: str | os.PathLike[str] | SequenceType[str | os.PathLike[str]], methods: SequenceType[str] | None = None
) -> dict[str, pd.DataFrame]:
    """The one reader of pair tables: each method's ``pairs.csv`` as its run published it, refused where
    ``results`` refuses; several folders: each method from the one folder holding it."""
    if not isinstance(output_dirs, (str, os.PathLike)):
        return _several_folders_tables(list(output_dirs), methods)
    folder = Path(output_dirs)

    names = scoring.readable_methods(folder, list(methods) if methods else None)
    return {method: scoring.load_pairs_table(folder, method) for method in names}


def _several_folders_tables(
    folders: list[str | os.PathLike[str]], methods: SequenceType[str] | None
) -> dict[str, pd.DataFrame]:
    found = method_folders(folders)
    wanted = list(methods) if methods else list(found)
    absent = [m for m in wanted if m not in found]
    if absent:
        raise method_outputs.ResultsError(
            f"no results for method {absent[0]!r} in {', '.join(map(str, folders))}; run it on the same pairs first"
        )
    tables: dict[str, pd.DataFrame] = {}
    for folder in dict.fromkeys(found[m] for m in wanted):
        tables.update(load_pairs_tables(folder, [m for m in wanted if found[m] == folder]))
    tables = {m: tables[m] for m in wanted}
    align_tables(tables)
    return tables


def measured_methods(output_dir: str | os.PathLike[str]) -> list[str]:
    """The methods of a folder whose pairs were matched here: imported scores have no matches to draw."""
    return [m for m in scoring.methods_with_results(Path(output_dir)) if "imported" not in load_run(output_dir, m)]


# ------------------------------------------------------------------ the table --
def best_per_column(table: pd.DataFrame, higher_is_better: bool | dict[str, bool] = True) -> pd.DataFrame:
    """True where a cell holds its column's best (ties all, NaN never); one flag or one a column."""
    marks = pd.DataFrame(False, index=table.index, columns=table.columns)
    for column in table.columns:
        values = pd.to_numeric(table[column], errors="coerce")
        if values.notna().sum() == 0:
            continue
        higher = higher_is_better if isinstance(higher_is_better, bool) else higher_is_better.get(column, True)
        best = values.max() if higher else values.min()
        marks[column] = values == best
    return marks


def resolve_cache_dir(
    output_dir: str | os.PathLike[str], cache_dir: str | os.PathLike[str] | None = None, method: str | None = None
) -> Path:
    """``cache_dir``, else the one ``method``'s run recorded (its run.json), else the one the runs'
    params recorded (params.resolved.yaml), else the default one."""
    if cache_dir:
        return Path(cache_dir)
    if method is not None:
        try:
            return Path(load_run(output_dir, method)["cache_dir"])
        except (OSError, ValueError, KeyError, TypeError):
            pass
    recorded = runs.resolved_params(output_dir)
    if recorded is not None:
        params = yaml.safe_load(recorded.read_text(encoding="utf-8")) or {}
        if isinstance(params, dict) and params.get("cache_dir"):
            return Path(params["cache_dir"])
    return fetch.cache_dir()


class IncomparableRunsError(method_outputs.ResultsError, ValueError):
    """Methods' results that cannot be compared pair by pair: different pairs or labels."""


def align_tables(tables: dict[str, pd.DataFrame]) -> pd.DataFrame:
    """One row a pair: query, reference, label and ``score:<method>`` per method (all on the same pairs and labels)."""
    if not tables:
        raise IncomparableRunsError("no methods to compare: pass at least one pairs table")
    methods = list(tables)
    base = tables[methods[0]][["query", "reference", "label"]].copy()
    keys = set(zip(base["query"], base["reference"]))
    for method in methods:
        table = tables[method]
        other = set(zip(table["query"], table["reference"]))
        if other != keys:
            raise IncomparableRunsError(
                f"methods {methods[0]!r} and {method!r} scored different pairs ({len(keys - other)} only in the first, "
                f"{len(other - keys)} only in the second); rerun them on the same pairs (same --limit)"
            )
        base = base.merge(
            table[["query", "reference", "label", "score"]].rename(
                columns={"label": "label:other", "score": f"score:{method}"}
            ),
            on=["query", "reference"],
            how="left",
            validate="one_to_one",
        )
        relabelled = base["label"].to_numpy() != base.pop("label:other").to_numpy()
        if relabelled.any():
            first = base[relabelled].iloc[0]
            raise IncomparableRunsError(
                f"methods {methods[0]!r} and {method!r} label {int(relabelled.sum())} of the same pairs differently "
                f"(e.g. {first['query']} {first['reference']}); rerun them with the same pair file and label rule"
            )
    return base
