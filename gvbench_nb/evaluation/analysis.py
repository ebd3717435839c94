"""The paper's analyses, computed only from written results.

Everything here reads what runs wrote - ``<output_dir>/results.csv``,
``<output_dir>/<method>/pairs.csv`` and ``run.json``, the match stores and the
feature cache - and never recomputes features. The analysis notebooks
(``notebooks/analysis_*.ipynb``) and ``python -m gvbench_nb report`` are thin over
these functions; the figures live in ``analysis_plots.py``.

Units: ``ap`` and ``max_recall`` are fractions in [0, 1] everywhere, ours and the
published ones alike (the paper's table, in %, is divided by 100 when read); tables meant
for people format them as %. Rows are keyed and labelled by (sequence, profile, method):
two protocols' numbers never share a row or a line.
"""

from __future__ import annotations

import json
import os
from collections.abc import Iterable
from collections.abc import Sequence as SequenceType
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import yaml

from gvbench_nb import config, pipeline, reference_values
from gvbench_nb import methods as method_registry
from gvbench_nb.data.sequences import frame_index

METRICS = ("ap", "max_recall")
PAPER_LABEL = reference_values.PAPER_LABEL  # how the paper's numbers are named in every table and figure
REPOSITORY_LABEL = reference_values.REPOSITORY_LABEL  # and the GV-Bench repository's
OURS_LABEL = "ours"
RUN_KEY = ["sequence", "profile", "method"]  # what identifies a run in every table and figure
TIME_COLUMNS = ("extract_seconds_per_pair", "match_seconds_per_pair", "verify_seconds_per_pair")


# ------------------------------------------------------------ finding results --
def ensure_results(
    params_file: str | os.PathLike[str], methods: SequenceType[str] = ("sift-nn",), **overrides: Any
) -> Path:
    """Run only the ``methods`` whose ``pairs.csv`` is missing, then make ``results.csv`` current.

    What an analysis notebook runs when it asks (``notebook.load_results(...,
    compute_missing=True)``): with everything present it does nothing but (when needed)
    re-evaluate. ``overrides`` go to ``config.load_params``
    (e.g. ``output_dir``, ``limit``). Returns the output folder.
    """
    params = config.load_params(params_file, **overrides)
    output_dir = Path(params["output_dir"])
    missing = [
        m
        for m in method_registry.expand_methods(list(methods))
        if not (pipeline.method_dir(output_dir, m) / "pairs.csv").is_file()
    ]
    if missing:
        sequence = config.prepare_sequence(params)
        for method in missing:
            pipeline.run_method_of_params(params, sequence, method)
    results_path = output_dir / "results.csv"
    have = set(pipeline.methods_with_results(output_dir))
    evaluated = set(pd.read_csv(results_path)["method"]) if results_path.is_file() else set()
    if missing or have != evaluated:
        pipeline.evaluate(output_dir)
    return output_dir


def find_output_dirs(
    root: str | os.PathLike[str] = config.PROJECT_ROOT / "outputs", sequences: SequenceType[str] | None = None
) -> list[Path]:
    """Sequence output folders under ``root`` holding a ``results.csv`` (sorted by name).

    With ``sequences``, exactly those folders (``root/<name>``); a missing one is an error.
    """
    root = Path(root)
    if sequences:
        folders = [root / name for name in sequences]
        absent = [str(f) for f in folders if not (f / "results.csv").is_file()]
        if absent:
            raise FileNotFoundError(
                f"no results.csv in {', '.join(absent)}; run them first (python -m gvbench_nb run params/NAME.yaml)"
            )
        return folders
    return sorted(p.parent for p in root.glob("*/results.csv"))


def load_results(output_dirs: Iterable[str | os.PathLike[str]]) -> pd.DataFrame:
    """``results.csv`` of several output folders, one table (plus an ``output_dir`` column)."""
    frames = []
    for folder in output_dirs:
        path = Path(folder) / "results.csv"
        if not path.is_file():
            raise FileNotFoundError(
                f"{path} is missing: evaluate that output folder first "
                "(python -m gvbench_nb run PARAMS, or analysis.ensure_results)"
            )
        frame = pd.read_csv(path)
        # Read only what a run published, unedited, from inputs unchanged since, on one set of pairs.
        pipeline.check_results_current(Path(folder), frame["method"], tables=["results.csv"])
        if "pairs_digest" in frame and frame["pairs_digest"].nunique() > 1:
            pipeline.check_one_binding(Path(folder), frame)
        frames.append(frame.assign(output_dir=str(Path(folder))))
    if not frames:
        raise ValueError("no output folders given: pass at least one folder holding results.csv")
    results = pd.concat(frames, ignore_index=True)
    if "fps" not in results:
        results["fps"] = 1.0 / results["seconds_per_pair"]
    return results


def load_run(output_dir: str | os.PathLike[str], method: str) -> dict[str, Any]:
    path = pipeline.method_dir(Path(output_dir), method) / "run.json"
    if not path.is_file():
        raise FileNotFoundError(f"{path} is missing: run {method!r} on that sequence first")
    return json.loads(path.read_text())


def load_pairs_tables(
    output_dir: str | os.PathLike[str], methods: SequenceType[str] | None = None
) -> dict[str, pd.DataFrame]:
    """Every method's ``pairs.csv`` of one output folder (default: all with results)."""
    methods = list(methods) if methods else pipeline.methods_with_results(Path(output_dir))
    return {m: pipeline.load_pairs_table(Path(output_dir), m) for m in methods}


# ------------------------------------------------------------------ the table --
def best_per_column(table: pd.DataFrame, higher_is_better: bool | dict[str, bool] = True) -> pd.DataFrame:
    """True where a cell holds its column's best value; ties are all marked, NaN never.

    ``higher_is_better`` may be one flag or a flag per column (e.g. seconds: lower).
    """
    marks = pd.DataFrame(False, index=table.index, columns=table.columns)
    for column in table.columns:
        values = pd.to_numeric(table[column], errors="coerce")
        if values.notna().sum() == 0:
            continue
        higher = higher_is_better if isinstance(higher_is_better, bool) else higher_is_better.get(column, True)
        best = values.max() if higher else values.min()
        marks[column] = values == best
    return marks


def load_paper_table(path: str | os.PathLike[str] | None = None) -> pd.DataFrame:
    """The paper's AP/MR (published in %) as fractions, with our method names where we have them.

    Default: the table shipped in ``gvbench_nb/reference_values``; ``path``: a file in the
    same format (``method,sequence,ap,max_recall`` in %), empty when it does not exist.
    Columns: paper_name, method (ours, or None for methods we do not implement),
    sequence, ap, max_recall.
    """
    columns = ["paper_name", "method", "sequence", *METRICS]
    if path is None:
        return reference_values.paper_table().rename(columns={"reference_name": "paper_name"})[columns]
    path = Path(path)
    if not path.is_file():
        return pd.DataFrame(columns=columns)
    raw = pd.read_csv(path)
    expected = {"method", "sequence", *METRICS}
    if not expected <= set(raw.columns):
        raise ValueError(f"{path}: expected columns {sorted(expected)}, got {list(raw.columns)}")
    by_paper_name = {conf["paper_name"]: name for name, conf in method_registry.METHODS.items()}
    table = raw.rename(columns={"method": "paper_name"})
    table["method"] = table["paper_name"].map(by_paper_name)
    for metric in METRICS:
        table[metric] = table[metric] / 100.0
    return table[columns]


def load_repository_table() -> pd.DataFrame:
    """The GV-Bench repository's published AP/MR (fractions), its matcher names as ``paper_name``
    and ours as ``method`` where they are the same method (``reference_values.REPOSITORY_METHODS``)."""
    return reference_values.repository_table().rename(columns={"reference_name": "paper_name"})


def source_label(source: str, profile: str | None = None) -> str:
    """How a row's values are named in tables and figures: ours always with the profile."""
    return f"{OURS_LABEL} ({profile} profile)" if source == OURS_LABEL else source


def duplicated_runs(results: pd.DataFrame) -> pd.DataFrame:
    """Rows of ``results`` sharing (sequence, profile, method) with another row."""
    return results[results.duplicated(RUN_KEY, keep=False)]


def join_paper_table(
    results: pd.DataFrame, paper: pd.DataFrame, repository: pd.DataFrame | None = None
) -> pd.DataFrame:
    """Long table of ours and the published values, one row a (method, profile, sequence, source).

    ``source`` is ``ours``, ``paper`` or ``GV-Bench repository``; ``profile`` is the
    protocol the values come from: ours, the run's profile; the paper's table, ``paper``
    (the hloc chain); the repository's, ``repository``. Published values are kept only
    beside a run of the same method, sequence and profile, so no row sets one protocol's
    numbers next to another's. ``label`` names the source for figures ("ours (paper profile)").
    Two runs with the same (sequence, profile, method) are an error, not a silent choice.
    """
    if "profile" not in results:
        raise ValueError(
            "the results have no profile column: evaluate the runs again "
            "(python -m gvbench_nb run PARAMS) so results.csv records each run's profile"
        )
    twice = duplicated_runs(results)
    if not twice.empty:
        where = twice.get("output_dir", pd.Series(["?"] * len(twice), index=twice.index))
        runs = "; ".join(f"{r.sequence}/{r.profile}/{r.method} in {w}" for r, w in zip(twice.itertuples(), where))
        raise ValueError(
            f"the same (sequence, profile, method) appears more than once: {runs}; pass only one output folder for each"
        )
    ours = results[["method", "profile", "sequence", *METRICS]].copy()
    ours["paper_name"] = ours["method"].map(method_registry.paper_name)
    ours["source"] = OURS_LABEL
    ran = set(zip(ours["method"], ours["sequence"], ours["profile"]))
    frames = [ours]
    for table, source, profile in ((paper, PAPER_LABEL, "paper"), (repository, REPOSITORY_LABEL, "repository")):
        if table is None or table.empty:
            continue
        # A boolean array, not a list: an empty list would select no columns instead of no rows.
        keep = np.array([(m, s, profile) in ran for m, s in zip(table["method"], table["sequence"])], dtype=bool)
        frames.append(table[keep].assign(source=source, profile=profile))
    columns = ["method", "paper_name", "profile", "sequence", "source", *METRICS]
    joined = pd.concat([f[columns] for f in frames], ignore_index=True)
    joined["label"] = [source_label(src, prof) for src, prof in zip(joined["source"], joined["profile"])]
    return joined


def results_table(joined: pd.DataFrame, metrics: SequenceType[str] = METRICS) -> pd.DataFrame:
    """Wide table: one row a (method, profile); columns (sequence, metric, source), ours beside
    the published values of the same protocol.

    Rows, sequences keep first-seen order; a published column exists only where it has values.
    """
    wide = joined.pivot_table(
        index=["method", "profile"], columns=["sequence", "source"], values=list(metrics), aggfunc="first"
    )
    wide = wide.reorder_levels([1, 0, 2], axis=1)
    sequence_order = list(dict.fromkeys(joined["sequence"]))
    row_order = [r for r in dict.fromkeys(zip(joined["method"], joined["profile"])) if r in wide.index]
    source_order = [OURS_LABEL, PAPER_LABEL, REPOSITORY_LABEL]
    keys = [(s, m, src) for s in sequence_order for m in metrics for src in source_order if (s, m, src) in wide.columns]
    wide = wide.loc[row_order, keys]
    wide.columns = pd.MultiIndex.from_tuples(keys, names=["sequence", "metric", "source"])
    wide.index = pd.MultiIndex.from_tuples(
        [(f"{m} ({method_registry.paper_name(m)})", p) for m, p in wide.index], names=["method", "profile"]
    )
    return wide


def paper_reference_table(
    paper: pd.DataFrame, methods: Iterable[str] | None = None, source: str = PAPER_LABEL
) -> pd.DataFrame:
    """A published table (all its sequences) for ``methods`` (its own names kept for the
    methods we do not implement when ``methods`` is None), columns (sequence, metric, source)."""
    if methods is not None:
        paper = paper[paper["method"].isin(list(methods))]
    wide = paper.assign(source=source).pivot_table(
        index="paper_name", columns=["sequence", "source"], values=list(METRICS), aggfunc="first"
    )
    wide = wide.reorder_levels([1, 0, 2], axis=1)
    keys = [(s, m, source) for s in dict.fromkeys(paper["sequence"]) for m in METRICS if (s, m, source) in wide.columns]
    wide = wide.loc[list(dict.fromkeys(paper["paper_name"])), keys]
    wide.columns = pd.MultiIndex.from_tuples(keys, names=["sequence", "metric", "source"])
    return wide


def style_results_table(wide: pd.DataFrame) -> Any:
    """The wide table as a pandas Styler: values in %, each column's best in bold,
    the published columns (paper, GV-Bench repository) in grey italics."""
    best = best_per_column(wide)

    def css(_: pd.DataFrame) -> pd.DataFrame:
        styles = pd.DataFrame("", index=wide.index, columns=wide.columns)
        for column in wide.columns:
            paper = column[-1] in (PAPER_LABEL, REPOSITORY_LABEL)
            base = "color: #666; font-style: italic;" if paper else ""
            styles[column] = [base + ("font-weight: bold;" if b else "") for b in best[column]]
        return styles

    return wide.style.format(lambda v: "-" if pd.isna(v) else f"{100 * v:.1f}").apply(css, axis=None)


def text_results_table(wide: pd.DataFrame) -> pd.DataFrame:
    """The wide table as strings in %, the best of each column marked with ``*``."""
    best = best_per_column(wide)
    text = wide.map(lambda v: "-" if pd.isna(v) else f"{100 * v:.1f}")
    return text.where(~best, text + "*")


# --------------------------------------------------------------------- runtime --
def runtime_table(results: pd.DataFrame) -> pd.DataFrame:
    """Seconds per pair split by stage (extraction amortised over the pairs using an
    image), total, FPS = 1 / seconds per pair, and MR - one row a (sequence, method)."""
    table = results[
        ["sequence", "method", "profile", "device", *TIME_COLUMNS, "seconds_per_pair", "max_recall", "ap"]
    ].copy()
    table["fps"] = 1.0 / table["seconds_per_pair"]
    return table


def resolve_cache_dir(output_dir: str | os.PathLike[str], cache_dir: str | os.PathLike[str] | None = None) -> Path:
    """The feature cache of an output folder: ``cache_dir`` when given, else the one its run
    recorded (``cache_dir`` in ``<output_dir>/params.resolved.yaml``), else the params'
    default ``<output_dir>/../cache`` (a folder written without ``run``)."""
    if cache_dir:
        return Path(cache_dir)
    recorded = Path(output_dir) / config.RESOLVED_PARAMS_NAME
    if recorded.is_file():
        params = yaml.safe_load(recorded.read_text(encoding="utf-8")) or {}
        if isinstance(params, dict) and params.get("cache_dir"):
            return Path(params["cache_dir"])
    return Path(output_dir).parent / "cache"


def image_size_of_run(
    output_dir: str | os.PathLike[str], method: str, run: dict[str, Any], cache_dir: Path
) -> tuple[int, int] | None:
    """Original (width, height) of the run's first query image: from the feature cache,
    else (dense matchers, or no cache here) the image file's header; None when neither is there."""
    first_query = pipeline.load_pairs_table(Path(output_dir), method)["query"].iloc[0]
    extractor = run["conf"].get("extractor")
    if extractor:
        store = pipeline.feature_store(cache_dir, extractor)
        try:
            key: str | None = pipeline.image_key(Path(run["image_root"]), first_query)
        except OSError:  # the image is gone: no key to look up
            key = None
        if key is not None and store.folder.is_dir() and key in store:
            size = store.read(key)["image_size"]
            store.close()
            return int(size[0]), int(size[1])
    path = Path(run["image_root"]) / first_query
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
        run = load_run(output_dir, method)
        environment = run["environment"]
        on_cpu = environment["device"] == "cpu" and "cpu_count" in environment
        cores = f", {environment['cpu_count']} cores" if on_cpu else ""
        devices.add(f"{environment['device']} ({environment.get('device_name') or '?'}{cores})")
        profiles.add(run["conf"]["profile"])
        # Dense matchers (no extractor) resize inside the matcher conf.
        resizing = run["conf"].get("extractor") or run["conf"]["matcher"]
        resize = resizing.get("resize_max")
        size = image_size_of_run(output_dir, method, run, resolve_cache_dir(output_dir, cache_dir))
        native = f"{size[0]}x{size[1]}" if size else "?"
        longest = f"{'=' if resizing.get('resize_force') else '<='}{resize}" if resize else "native"
        fixed = resizing.get("resize_to")
        sizes.add(
            f"{resizing['name']}: {native}, "
            + (f"resized to {fixed[0]}x{fixed[1]}" if fixed else f"longest side {longest}")
        )
    return (
        f"device {' / '.join(sorted(devices))}; profile {' / '.join(sorted(profiles))}; "
        f"images {'; '.join(sorted(sizes))}"
    )


# ------------------------------------------------------------------- inliers --
def normalised_inliers(table: pd.DataFrame) -> pd.Series:
    """Inliers / the method's largest inlier count (the paper's normalisation; 0 when all are 0)."""
    largest = table["num_inliers"].max()
    return table["num_inliers"] / largest if largest > 0 else table["num_inliers"] * 0.0


def normalised_inlier_table(tables: dict[str, pd.DataFrame]) -> pd.DataFrame:
    """Long table: method, pair_index, label, num_inliers, normalised_inliers."""
    frames = [
        t[["pair_index", "label", "num_inliers"]].assign(method=m, normalised_inliers=normalised_inliers(t))
        for m, t in tables.items()
    ]
    return pd.concat(frames, ignore_index=True)


def inlier_overlap_summary(table: pd.DataFrame) -> dict[str, float]:
    """What caps MR: the top false pair's score and the true pairs that do not beat it.

    ``true_above_top_false`` is the share of true pairs scoring strictly above every
    false pair - the recall reachable at 100% precision, i.e. MR.
    """
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


def inlier_overlap_table(tables: dict[str, pd.DataFrame]) -> pd.DataFrame:
    return pd.DataFrame([{"method": m, **inlier_overlap_summary(t)} for m, t in tables.items()])


# -------------------------------------------------------------- failures --
def read_poses(image_root: str | os.PathLike[str]) -> pd.DataFrame | None:
    """``<image_root>/poses.csv`` (the sample generator's exact poses) indexed by image, or None."""
    path = Path(image_root) / "poses.csv"
    if not path.is_file():
        return None
    return pd.read_csv(path).set_index("image")


def _frame_offset(query: str, reference: str) -> float:
    try:
        return float(abs(frame_index(query) - frame_index(reference)))
    except ValueError:
        return float("nan")


def ground_truth_offsets(table: pd.DataFrame, image_root: str | os.PathLike[str] | None = None) -> pd.DataFrame:
    """Per pair: ``frame_offset`` |i - j| (frame-named images, else NaN) and, when
    ``<image_root>/poses.csv`` exists, ``distance_m`` between camera centres and
    ``heading_deg`` between optical axes."""
    out = pd.DataFrame(index=table.index)
    out["frame_offset"] = [_frame_offset(q, r) for q, r in zip(table["query"], table["reference"])]
    poses = read_poses(image_root) if image_root is not None else None
    if poses is not None:
        assert image_root is not None, "poses are read from an image_root"
        missing = sorted(set(table["query"]).union(table["reference"]) - set(poses.index))
        if missing:
            raise KeyError(
                f"{Path(image_root) / 'poses.csv'} has no pose for {len(missing)} images, e.g. {missing[:3]}"
            )
        centres = poses[["x", "y", "z"]].to_numpy(dtype=float)
        axes = poses[["r02", "r12", "r22"]].to_numpy(dtype=float)  # optical axis (camera z) in the world
        row = {name: i for i, name in enumerate(poses.index)}
        q = np.array([row[n] for n in table["query"]], dtype=int)
        r = np.array([row[n] for n in table["reference"]], dtype=int)
        out["distance_m"] = np.linalg.norm(centres[q] - centres[r], axis=1)
        cosine = np.einsum("ij,ij->i", axes[q], axes[r]) / (
            np.linalg.norm(axes[q], axis=1) * np.linalg.norm(axes[r], axis=1)
        )
        out["heading_deg"] = np.degrees(np.arccos(np.clip(cosine, -1.0, 1.0)))
    return out


def top_false_positives(table: pd.DataFrame, k: int = 5) -> pd.DataFrame:
    """The ``k`` highest-scoring false pairs (label 0); ties broken by pair_index."""
    false = table[table["label"] == 0]
    return false.sort_values(["score", "pair_index"], ascending=[False, True], kind="mergesort").head(k)


def top_false_negatives(table: pd.DataFrame, k: int = 5) -> pd.DataFrame:
    """The ``k`` lowest-scoring true pairs (label 1); ties broken by pair_index."""
    true = table[table["label"] == 1]
    return true.sort_values(["score", "pair_index"], ascending=[True, True], kind="mergesort").head(k)


def failures_table(
    tables: dict[str, pd.DataFrame], k: int = 5, image_root: str | os.PathLike[str] | None = None
) -> pd.DataFrame:
    """Top false positives and false negatives of every method with their offsets."""
    frames = []
    for method, table in tables.items():
        for kind, rows in (
            ("false_positive", top_false_positives(table, k)),
            ("false_negative", top_false_negatives(table, k)),
        ):
            rows = rows.assign(method=method, kind=kind, rank=np.arange(1, len(rows) + 1))
            frames.append(rows.join(ground_truth_offsets(rows, image_root)))
    columns = ["method", "kind", "rank", "pair_index", "query", "reference", "label", "score", "num_matches"]
    frame = pd.concat(frames, ignore_index=True)
    return frame[columns + [c for c in ("frame_offset", "distance_m", "heading_deg") if c in frame]]


def near_miss_false_positives(
    table: pd.DataFrame,
    offsets: pd.DataFrame,
    top_k: int = 20,
    column: str = "frame_offset",
    low: float = 3,
    high: float = 5,
) -> dict[str, Any]:
    """How many of the ``top_k`` highest-scoring false pairs lie just outside the
    ground-truth threshold (``low <= offset <= high``), against the share of such
    pairs among all false pairs: the ground-truth ambiguity the paper discusses."""
    false = table["label"] == 0
    near = offsets[column].between(low, high)
    top = top_false_positives(table, top_k)
    n_near_top = int(near.loc[top.index].sum())
    return {
        "top_k": int(len(top)),
        "column": column,
        "low": low,
        "high": high,
        "near_in_top": n_near_top,
        "near_share_in_top": n_near_top / max(len(top), 1),
        "near_share_all_false": float(near[false].mean()) if false.any() else float("nan"),
        "top_k_min_score": float(top["score"].min()) if len(top) else float("nan"),
    }


def match_lines(
    output_dir: str | os.PathLike[str],
    method: str,
    query: str,
    reference: str,
    cache_dir: str | os.PathLike[str] | None = None,
) -> dict[str, np.ndarray]:
    """Matched points of one pair (original pixels) and its inlier mask, from the stores.

    Reads the run's match store and, for detector-based methods, the keypoints in the
    feature cache (``<output_dir>/../cache`` unless ``cache_dir``); dense matchers
    store their matched points with the matches.
    """
    output_dir = Path(output_dir)
    run = load_run(output_dir, method)
    matches = pipeline.match_store(output_dir, run["conf"])
    key = pipeline.pair_key(Path(run["image_root"]), query, reference, int(run["seed"]))
    if key not in matches:
        raise KeyError(f"pair {query} {reference} is not in the match store {matches.folder} of {method!r}")
    entry = matches.read(key)
    matches.close()
    inlier_mask = entry["inlier_mask"].astype(bool)
    if "points0" in entry:  # dense matcher
        return {"points0": entry["points0"], "points1": entry["points1"], "inlier_mask": inlier_mask}
    features = pipeline.feature_store(resolve_cache_dir(output_dir, cache_dir), run["conf"]["extractor"])
    image_root = Path(run["image_root"])
    try:
        points0 = features.read(pipeline.image_key(image_root, query))["keypoints"]
        points1 = features.read(pipeline.image_key(image_root, reference))["keypoints"]
    except KeyError as error:
        raise KeyError(
            f"{error}; the run's cache {features.folder.parent.parent} does not hold that pair's features: "
            "rerun its method (python -m gvbench_nb run PARAMS --methods NAME) to fill it"
        ) from None
    finally:
        features.close()
    pair_matches = entry["matches"].astype(int).reshape(-1, 2)
    # float32: the cache may hold float16 keypoints (as hloc stores them).
    return {
        "points0": points0[pair_matches[:, 0]].astype(np.float32),
        "points1": points1[pair_matches[:, 1]].astype(np.float32),
        "inlier_mask": inlier_mask,
    }


# ------------------------------------------------------------------ bootstrap --
def weighted_ap_max_recall(
    labels: np.ndarray, scores: np.ndarray, weights: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """AP and MR of many weightings of the same pairs at once.

    ``weights`` is (B, N): how often each pair counts in each of B resamples. Equals
    scikit-learn's ``average_precision_score`` and our ``max_recall_at_full_precision``
    on the repeated pairs (tied scores form one threshold, as there). NaN where a
    resample holds no true pair.
    """
    labels = np.asarray(labels).astype(bool)
    scores = np.asarray(scores, dtype=np.float64)
    weights = np.atleast_2d(np.asarray(weights, dtype=np.float64))
    order = np.argsort(-scores, kind="mergesort")
    sorted_scores = scores[order]
    # Last index of each run of equal scores: the curve's threshold points.
    ends = np.r_[np.nonzero(np.diff(sorted_scores))[0], len(scores) - 1]
    w = weights[:, order]
    positive = labels[order]
    true_positives = np.cumsum(w * positive, axis=1)[:, ends]
    false_positives = np.cumsum(w * ~positive, axis=1)[:, ends]
    total_positive = true_positives[:, -1]
    with np.errstate(invalid="ignore", divide="ignore"):
        predicted = true_positives + false_positives
        precision = np.where(predicted > 0, true_positives / np.where(predicted > 0, predicted, 1), 1.0)
        gained = np.diff(true_positives, axis=1, prepend=0.0)
        ap = (gained * precision).sum(axis=1) / total_positive
        reachable = np.where(false_positives == 0, true_positives, 0.0).max(axis=1)
        max_recall = reachable / total_positive
    invalid = total_positive <= 0
    ap[invalid] = np.nan
    max_recall[invalid] = np.nan
    return ap, max_recall


def query_resample_weights(query_codes: np.ndarray, n_resamples: int, seed: int) -> np.ndarray:
    """(B, N) pair weights: each resample draws the queries with replacement and every
    pair counts as often as its query was drawn (pairs of a query stay together)."""
    query_codes = np.asarray(query_codes)
    n_queries = int(query_codes.max()) + 1
    rng = np.random.default_rng(seed)
    drawn = rng.integers(0, n_queries, size=(n_resamples, n_queries))
    flat = drawn + n_queries * np.arange(n_resamples)[:, None]
    counts = np.bincount(flat.ravel(), minlength=n_resamples * n_queries).reshape(n_resamples, n_queries)
    return counts[:, query_codes]


class IncomparableRunsError(pipeline.ResultsError, ValueError):
    """Methods' results that cannot be compared pair by pair: different pairs or labels."""


def align_tables(tables: dict[str, pd.DataFrame]) -> pd.DataFrame:
    """One row a pair: query, reference, label and a ``score:<method>`` column per method.

    All methods must have scored the same pairs under the same labels (a bootstrap
    compares them pair by pair).
    """
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


@dataclass
class Bootstrap:
    """Resampled AP and MR of several methods on the same query resamples."""

    methods: list[str]
    estimates: pd.DataFrame  # index method, columns ap, max_recall (all queries)
    samples: dict[str, pd.DataFrame]  # metric -> (B rows, one column a method)
    n_queries: int
    n_pairs: int
    seed: int

    def intervals(self, level: float = 0.95) -> pd.DataFrame:
        """Percentile CIs: method, metric, estimate, low, high, n_valid (resamples with a true pair)."""
        tail = 100 * (1 - level) / 2
        rows = []
        for metric, frame in self.samples.items():
            for method in self.methods:
                values = frame[method].to_numpy()
                valid = values[~np.isnan(values)]
                low, high = np.percentile(valid, [tail, 100 - tail]) if len(valid) else (np.nan, np.nan)
                rows.append(
                    {
                        "method": method,
                        "metric": metric,
                        "estimate": self.estimates.loc[method, metric],
                        "low": low,
                        "high": high,
                        "n_valid": len(valid),
                    }
                )
        return pd.DataFrame(rows)

    def pairwise(self, metric: str = "max_recall", level: float = 0.975) -> pd.DataFrame:
        """Every ordered pair of methods: the share of resamples where A beats B, ties,
        and ``a_better`` = A beats B in more than ``level`` of them."""
        frame = self.samples[metric]
        rows = []
        for a in self.methods:
            for b in self.methods:
                if a == b:
                    continue
                both = frame[[a, b]].dropna()
                wins = float((both[a] > both[b]).mean()) if len(both) else float("nan")
                ties = float((both[a] == both[b]).mean()) if len(both) else float("nan")
                rows.append(
                    {
                        "metric": metric,
                        "method_a": a,
                        "method_b": b,
                        "a_beats_b": wins,
                        "tied": ties,
                        "a_better": bool(wins > level),
                    }
                )
        return pd.DataFrame(rows)

    def ranking_matrix(self, metric: str = "max_recall", level: float = 0.975) -> pd.DataFrame:
        """Square table: '>' where the row method is significantly better than the column's,
        '<' where worse, '~' where neither."""
        pairs = self.pairwise(metric, level)
        matrix = pd.DataFrame("", index=self.methods, columns=self.methods)
        for row in pairs.itertuples():
            reverse = pairs[(pairs.method_a == row.method_b) & (pairs.method_b == row.method_a)].iloc[0]
            matrix.loc[row.method_a, row.method_b] = ">" if row.a_better else ("<" if reverse.a_better else "~")
        return matrix


def bootstrap(tables: dict[str, pd.DataFrame], n_resamples: int = 1000, seed: int = 0) -> Bootstrap:
    """Resample QUERIES with replacement (seeded) and recompute every method's AP and MR.

    The same resamples serve every method (a paired bootstrap), so pairwise
    comparisons are fair. 1000 resamples of 2000 pairs take well under a second a method.
    """
    aligned = align_tables(tables)
    query_codes = pd.factorize(aligned["query"])[0]
    weights = query_resample_weights(query_codes, n_resamples, seed)
    labels = aligned["label"].to_numpy()
    methods = list(tables)
    samples: dict[str, dict[str, np.ndarray]] = {"ap": {}, "max_recall": {}}
    estimates = {}
    for method in methods:
        scores = aligned[f"score:{method}"].to_numpy(dtype=float)
        samples["ap"][method], samples["max_recall"][method] = weighted_ap_max_recall(labels, scores, weights)
        ap, max_recall = weighted_ap_max_recall(labels, scores, np.ones((1, len(labels))))
        estimates[method] = {"ap": ap[0], "max_recall": max_recall[0]}
    return Bootstrap(
        methods=methods,
        estimates=pd.DataFrame(estimates).T,
        samples={metric: pd.DataFrame(values) for metric, values in samples.items()},
        n_queries=int(query_codes.max()) + 1,
        n_pairs=len(aligned),
        seed=seed,
    )
