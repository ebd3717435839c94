"""From per-pair tables to results: what each method's results are bound to (pairs, labels,
images), AP/MR per method, and the checks that a table is still the one its inputs made.
"""

from __future__ import annotations

import hashlib
import os
from collections.abc import Iterable
from collections.abc import Sequence as SequenceType
from pathlib import Path
from typing import Any

import pandas as pd

from gvbench_nb import methods as method_registry
from gvbench_nb.data.sequences import Sequence
from gvbench_nb.io_utils import atomic_write_csv, file_sha256
from gvbench_nb.protocol.images import ImageReadError
from gvbench_nb.protocol.metrics import evaluate_scores
from gvbench_nb.runner import image_features, method_outputs, runs


def pairs_digest(rows: Iterable[tuple[str, str, int]]) -> str:
    """SHA-256 of the (query, reference, label) rows a method scored, in order: two tables with
    the same digest were scored on the same pairs with the same labels."""
    text = "".join(f"{query}\t{reference}\t{int(label)}\n" for query, reference, label in rows)
    return hashlib.sha256(text.encode()).hexdigest()


def table_pairs_digest(table: pd.DataFrame) -> str:
    return pairs_digest(zip(table["query"], table["reference"], table["label"]))


def images_digest(image_root: Path, names: Iterable[str]) -> str:
    """BLAKE2b of the images' names and content keys: changes when any image's bytes change."""
    digest = hashlib.blake2b(digest_size=20)
    for name in sorted(set(names)):
        digest.update(f"{name}\t{image_features.image_key(image_root, name)}\n".encode())
    return digest.hexdigest()


def sequence_binding(sequence: Sequence) -> dict[str, Any]:
    """What a method's results are bound to: the pairs and labels scored and the images' contents (the
    pair file they came from, and its SHA-256, are named once, in run.json's ``pairs``)."""
    return {
        "pairs_digest": pairs_digest((p.query, p.reference, p.label) for p in sequence.pairs),
        "images_digest": images_digest(sequence.image_root, sequence.images),
    }


def load_pairs_table(output_dir: Path, method: str) -> pd.DataFrame:
    path = method_outputs.method_dir(output_dir, method) / "pairs.csv"
    if not path.is_file():
        raise method_outputs.ResultsError(f"no results for method {method!r}: {path} is missing; run the method first")
    # Names stay strings whatever they read ("NA", "null"); an empty measurement is missing
    # (the seconds and counts of imported scores, which no run here measured).
    names = {"query", "reference", "method", "profile"}
    measured = {column: [""] for column in method_outputs.PAIRS_COLUMNS if column not in names}
    table = pd.read_csv(path, keep_default_na=False, na_values=measured)
    # A table written without the inlier keypoint counts reads them as not measured.
    missing = [column for column in method_outputs.INLIER_KEYPOINT_COUNTS if column not in table]
    return table.assign(**dict.fromkeys(missing, float("nan"))) if missing else table


def methods_with_results(output_dir: Path) -> list[str]:
    """The methods a run holds, in registry order, then any others; or the rows an output folder shows
    (``runs.current``: a method, or a method under one of its recipes, such as ``orb-nn (paper profile)``)."""
    if not runs.is_run(output_dir):
        return list(runs.current(output_dir).entries)
    found = {p.parent.name for p in Path(output_dir).glob("*/pairs.csv")}
    ordered = [m for m in method_registry.method_names() if m in found]
    return ordered + sorted(found - set(ordered))


def timers_source(run: dict[str, Any]) -> str:
    """Whose timers a method's seconds are: ``this run`` (it computed every image and pair, or
    another method of the same run extracted the images it shares), ``cached`` (every one came
    from the cache: the seconds are those of the runs that computed them), ``partly cached``, or
    ``imported`` (scores computed elsewhere: no seconds)."""
    if "imported" in run:
        return "imported"
    this_run = run.get("this_run", {})
    extraction, matching = this_run.get("extraction", {}), this_run.get("matching", {})
    earlier = extraction.get("cached_by_this_run", 0)
    reused = extraction.get("cached", 0) - earlier + matching.get("cached", 0)
    computed = extraction.get("extracted", 0) + earlier + matching.get("matched", 0)
    if not reused:
        return "this run"
    return "cached" if not computed else "partly cached"


def evaluate(output_dir: Path, methods: list[str] | None = None, write: bool = True) -> pd.DataFrame:
    """AP, MR and seconds per pair for every method with results; writes ``results.csv``. Methods
    scored on other pairs or labels (``pairs_digest``) are refused, naming the rows."""
    output_dir = Path(output_dir)
    methods = methods or methods_with_results(output_dir)
    if not methods:
        what = (
            "does not exist" if not output_dir.exists() else "holds no method results (no run of a method under runs/)"
        )
        raise method_outputs.ResultsError(
            f"{output_dir} {what}; give the output_dir of a finished run, or run a method first "
            "(python -m gvbench_nb run PARAMS)"
        )
    rows = []
    for method in methods:
        table, run = load_pairs_table(output_dir, method), method_outputs.read_run_json(output_dir, method)
        where = str(method_outputs.method_dir(output_dir, method) / "pairs.csv")
        metrics = evaluate_scores(table["label"].to_numpy(), table["score"].to_numpy(), where=where)
        rows.append(
            {
                "sequence": run["sequence"],
                "method": method,
                "paper_name": run["conf"]["paper_name"],
                "profile": run["conf"]["profile"],
                **metrics,
                "extract_seconds_per_pair": table["extract_seconds"].mean(),
                "match_seconds_per_pair": table["match_seconds"].mean(),
                "verify_seconds_per_pair": table["verify_seconds"].mean(),
                "seconds_per_pair": (
                    table["extract_seconds"] + table["match_seconds"] + table["verify_seconds"]
                ).mean(),
                "device": run["environment"]["device"],
                # >1: the seconds above include waiting for cores shared by concurrent images/pairs
                "jobs": run.get("this_run", {}).get("jobs", 1),
                "timers": timers_source(run),
                "pairs_digest": table_pairs_digest(table)[:12],
                "finished_at": run.get("finished_at"),
            }
        )
    results = pd.DataFrame(rows)
    check_one_binding(output_dir, results)
    if write and (not runs.is_run(output_dir) or output_dir.name.startswith(runs.BUILDING)):  # a sealed run stays
        atomic_write_csv(output_dir / "results.csv", results)
    return results


def refresh_view(output_dir: Path) -> pd.DataFrame:
    """Write the folder's ``results.csv`` from the runs it shows; made again while another run landed
    meanwhile, so the file written last is of every run then finished."""
    while True:
        before = [folder.name for folder, _ in runs.finished_runs(output_dir)]
        results = evaluate(output_dir)
        if [folder.name for folder, _ in runs.finished_runs(output_dir)] == before:
            return results


def check_one_binding(output_dir: Path, results: pd.DataFrame) -> None:
    """Refuse a results table whose methods scored different pairs or labels, naming the rows."""
    groups = results.groupby("pairs_digest", sort=False)["method"].apply(list)
    if len(groups) > 1:
        described = "; ".join(f"{', '.join(names)}: pairs {digest}" for digest, names in groups.items())
        raise method_outputs.ResultsError(
            f"{output_dir}: its methods were scored on different pairs or labels ({described}), so their AP and MR "
            "do not compare; rerun them on one pair file, or give each pair file its own output_dir"
        )


def changed_inputs(output_dir: Path, methods: Iterable[str]) -> dict[str, str]:
    """Methods whose inputs changed since they ran: method -> what changed (the pair file's
    SHA-256, or the images' contents); inputs no longer there to check are not reported."""
    changed = {}
    for method in methods:
        run = method_outputs.read_run_json(output_dir, method)
        pairs = run.get("pairs") or {}
        pairs_file = pairs.get("pairs_file")
        if pairs_file and Path(pairs_file).is_file() and file_sha256(pairs_file) != pairs.get("pairs_sha256"):
            changed[method] = f"the pair file {pairs_file} changed"
            continue
        recorded = (run.get("binding") or {}).get("images_digest")
        root = Path(run.get("image_root", ""))
        if recorded and root.is_dir():
            table = load_pairs_table(output_dir, method)
            try:
                now = images_digest(root, [*table["query"], *table["reference"]])
            except ImageReadError:
                changed[method] = f"an image under {root} is gone"
                continue
            if now != recorded:
                changed[method] = f"images under {root} changed"
    return changed


def left_out(output_dir: str | os.PathLike[str]) -> list[str]:
    """The runs an output folder's view leaves out, a line each saying why and how to show it."""
    return [] if runs.is_run(output_dir) else list(runs.current(output_dir).left_out.values())


def readable_methods(output_dir: str | os.PathLike[str], methods: SequenceType[str] | None = None) -> list[str]:
    """The check every reader of results runs first: ``methods`` (default: all) shown by the folder
    (or held by the run), their inputs unchanged, all on the same pairs and labels; the methods."""
    folder = Path(output_dir)
    if not folder.is_dir():
        evaluate(folder, write=False)  # says the folder does not exist
    runs.check_owned(folder)
    shown = methods_with_results(folder)
    if not methods:
        methods = shown
        if not methods:
            evaluate(folder, write=False)  # says the folder holds no results
    absent = [m for m in methods if m not in shown]
    if absent:
        why = {} if runs.is_run(folder) else runs.current(folder).left_out
        if absent[0] in why:
            raise method_outputs.ResultsError(
                f"{folder} does not show {absent[0]} beside its other methods: {why[absent[0]]}"
            )
        load_pairs_table(folder, absent[0])  # names the missing pairs.csv
    methods = list(methods)
    changed = changed_inputs(folder, methods)
    if changed:
        described = "; ".join(f"{method}: {why}" for method, why in changed.items())
        raise method_outputs.ResultsError(
            f"{folder}: results computed from inputs that have changed since ({described}); run those methods "
            f"again (python -m gvbench_nb run PARAMS --methods {','.join(m.split(' (')[0] for m in changed)} --output-dir {runs.output_folder(folder)})"
        )
    digests = [table_pairs_digest(load_pairs_table(folder, m))[:12] for m in methods]
    check_one_binding(folder, pd.DataFrame({"method": methods, "pairs_digest": digests}))
    return methods
