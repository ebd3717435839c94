"""Per-pair scores computed elsewhere, in and out: the GV-Bench authors' ``.npy`` (a pickled dict,
their ``.asset/replicate.md``; read by an unpickler that builds only numpy arrays and plain data) and
a ``query reference label score`` table, added to an output folder as a run of one method."""

from __future__ import annotations

import csv
import importlib
import io
import pickle
import shlex
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from gvbench_nb import GVBenchError, __version__
from gvbench_nb import methods as method_registry
from gvbench_nb.data.sequences import Pair, Sequence, check_pairs, name_problem, read_text
from gvbench_nb.io_utils import atomic_write_csv, atomic_write_json, file_sha256
from gvbench_nb.protocol.metrics import evaluate_scores, pr_curve
from gvbench_nb.runner import method_outputs, runs, scoring

TABLE_COLUMNS = ["query", "reference", "label", "score"]
IMPORTED_PROFILE = "imported"  # the profile column of an imported method: we did not run its chain
# What a pickled numpy array, numpy scalar or dtype needs (numpy 1 writes numpy.core, numpy 2 numpy._core).
_CORE = "numpy._core" if int(np.__version__.split(".")[0]) >= 2 else "numpy.core"
_NUMPY_GLOBALS = {("numpy", "ndarray"): np.ndarray, ("numpy", "dtype"): np.dtype} | {
    (f"{spelling}.{module}", name): getattr(importlib.import_module(f"{_CORE}.{module}"), name)
    for spelling in ("numpy.core", "numpy._core")
    for module, name in (("multiarray", "_reconstruct"), ("multiarray", "scalar"), ("numeric", "_frombuffer"))
}


class ScoreFileError(GVBenchError, ValueError):
    """A score file cannot be imported: unreadable, not plain data, or its columns do not fit."""


class _PlainDataUnpickler(pickle.Unpickler):
    def find_class(self, module: str, name: str) -> Any:
        try:
            return _NUMPY_GLOBALS[(module, name)]
        except KeyError:
            raise pickle.UnpicklingError(f"{module}.{name}") from None


def load_authors_npy(path: Path) -> dict[str, Any]:
    """The dict an ``np.save(path, {...})`` wrote, built without running anything the file names."""
    with open(path, "rb") as handle:
        try:
            version = np.lib.format.read_magic(handle)
            read_header = {(1, 0): np.lib.format.read_array_header_1_0, (2, 0): np.lib.format.read_array_header_2_0}
            _, _, dtype = read_header[version](handle)
        except (ValueError, KeyError, EOFError) as error:
            raise ScoreFileError(f"{path} is not a .npy file numpy 1 or 2 writes ({error})") from None
        if not dtype.hasobject:
            raise ScoreFileError(f"{path} holds a plain {dtype} array, not the GV-Bench dict of per-pair outputs")
        try:
            loaded = _PlainDataUnpickler(io.BytesIO(handle.read())).load()
        except pickle.UnpicklingError as error:
            raise ScoreFileError(
                f"{path} holds a pickled {error}, which is not plain data (arrays, lists, dicts, strings, numbers), "
                "so it was refused without running it; ask for the file again or import a table "
                "'query reference label score' instead"
            ) from None
        except Exception as error:  # a truncated or garbled pickle
            raise ScoreFileError(f"{path}: its pickled data cannot be read ({type(error).__name__}: {error})") from None
    value = loaded.item() if isinstance(loaded, np.ndarray) and loaded.shape == () else loaded
    if not isinstance(value, dict):
        raise ScoreFileError(
            f"{path} holds a pickled {type(value).__name__}, not the GV-Bench dict of per-pair outputs"
        )
    return value


def _inlier_counts(inliers: Any) -> np.ndarray:
    """The authors' ``inliers``: one array of inlier point rows a pair, or (their multiprocess
    evaluation) one count a pair."""
    if isinstance(inliers, np.ndarray) and inliers.dtype != object:
        return inliers.astype(np.float64).ravel()
    return np.array([len(item) if np.ndim(item) else float(item) for item in inliers], dtype=np.float64)


def authors_table(values: dict[str, Any], where: str) -> tuple[pd.DataFrame, dict[str, Any]]:
    """(query, reference, label, score, num_inliers) from the authors' dict, and what it states
    about itself (AP, MR). The score is the inlier count where the file has it, else ``prob``
    (the counts divided by their maximum: the same ranking, so the same AP and MR)."""
    missing = [key for key in ("qImages", "rImages", "gt") if key not in values]
    if missing or not ("inliers" in values or "prob" in values):
        raise ScoreFileError(
            f"{where} lacks {', '.join(missing) or 'inliers and prob'}: the GV-Bench .npy holds qImages, rImages, "
            "gt and inliers (or prob), one entry a pair"
        )
    lengths = {key: len(values[key]) for key in ("qImages", "rImages", "gt", "inliers", "prob") if key in values}
    if len(set(lengths.values())) != 1:
        raise ScoreFileError(f"{where}: its per-pair entries differ in length ({lengths}); the file is damaged")
    counts = _inlier_counts(values["inliers"]) if "inliers" in values else None
    score = counts if counts is not None else np.asarray(values["prob"], dtype=np.float64).ravel()
    rows = zip(range(len(score)), map(str, values["qImages"]), map(str, values["rImages"]), values["gt"])
    table = _checked_table([(i, q, r, _label_text(g)) for i, q, r, g in rows], score, where, "pair")
    table["num_inliers"] = counts if counts is not None else np.nan
    stated = {"ap": values.get("average_precision"), "max_recall": values.get("Max Recall")}
    return table, {k: float(v) for k, v in stated.items() if v is not None}


def _label_text(value: Any) -> str:
    """A label as a pair file writes it: ints, bools and numeric text equal to 0 or 1 are "0" or "1"."""
    try:
        number = float(value)
    except (TypeError, ValueError):
        return str(value)
    return str(int(number)) if number in (0, 1) else str(value)


def _checked_table(rows: list[tuple[int, str, str, str]], scores: np.ndarray, where: str, unit: str) -> pd.DataFrame:
    """Imported pairs checked as a pair file's are (``sequences.check_pairs``: normalised paths, no
    duplicate, self-pair or pair given both ways, labels 0 or 1), each score finite."""
    pairs = check_pairs(rows, where, unit)
    bad = np.flatnonzero(~np.isfinite(scores))
    if len(bad):
        number, query, reference, _ = rows[int(bad[0])]
        at = f"{where}:{number}" if unit == "line" else f"{where}: {unit} {number}"
        raise ScoreFileError(
            f"{at}: score {scores[bad[0]]} of pair {query} {reference} is not a finite number ({len(bad)} such "
            "scores in the file); give every pair a finite score"
        )
    table = pd.DataFrame(pairs, columns=["query", "reference", "label"])
    table["score"] = scores
    table["where"] = [f"{where}:{row[0]}" if unit == "line" else f"{where}: {unit} {row[0]}" for row in rows]
    return table


def check_images(table: pd.DataFrame, sequence: str, image_root: Path) -> None:
    """The imported pairs' images are files under ``image_root``, and no pair is of two images with one
    content (``input_checks.check_distinct_contents``, as for a run's pairs), each refusal naming the row."""
    from gvbench_nb.runner import input_checks  # OpenCV: only an import given its images reads them

    pairs = [Pair(*row) for row in zip(table["query"], table["reference"], table["label"])]
    named = Sequence(sequence, image_root, pairs)
    named.check_images()
    input_checks.check_distinct_contents(named, lambda index: str(table["where"].iloc[index]))


def read_table(path: Path) -> pd.DataFrame:
    """A table ``query reference label score``: CSV or whitespace, with or without that header;
    a path holding spaces is written in double quotes (as in GV-Bench's pair files)."""
    rows: list[tuple[int, str, str, str]] = []
    scores: list[float] = []
    for number, raw in enumerate(read_text(path, "a table of scores").splitlines(), start=1):
        line = raw.strip()
        if not line or line.startswith("#"):
            continue
        try:
            fields = [f.strip() for f in next(csv.reader([line]))] if "," in line else shlex.split(line)
        except ValueError as error:  # an unclosed quote
            raise ScoreFileError(f"{path}:{number}: {error}; close the quote around the path") from None
        if not rows and [f.lower() for f in fields] == TABLE_COLUMNS:
            continue
        if len(fields) != 4:
            raise ScoreFileError(
                f"{path}:{number}: expected 4 fields 'query reference label score', got {len(fields)} in {line[:80]!r}; "
                'write a path holding spaces in double quotes, "like this.jpg"'
            )
        try:
            scores.append(float(fields[3]))
        except ValueError:
            raise ScoreFileError(
                f"{path}:{number}: score {fields[3]!r} of pair {fields[0]} {fields[1]} is not a number"
            ) from None
        rows.append((number, fields[0], fields[1], _label_text(fields[2])))
    table = _checked_table(rows, np.array(scores, dtype=np.float64), str(path), "line")
    table["num_inliers"] = np.nan
    return table


NPY_MAGIC = b"\x93NUMPY"  # how every .npy begins: the format is read from the content, not the name


def read_scores(path: str | Path) -> tuple[pd.DataFrame, dict[str, Any], str]:
    """(table, what the file states about itself, its format) of a score file."""
    path = Path(path)
    if not path.is_file():
        raise ScoreFileError(f"{path} does not exist; give the .npy or the table of scores to import")
    with open(path, "rb") as handle:
        npy = handle.read(len(NPY_MAGIC)) == NPY_MAGIC
    if npy:
        table, stated = authors_table(load_authors_npy(path), str(path))
        return table, stated, "gvbench-npy"
    return read_table(path), {}, "table"


def _pairs_csv(table: pd.DataFrame, method: str) -> pd.DataFrame:
    out = pd.DataFrame(dict.fromkeys(method_outputs.PAIRS_COLUMNS, np.nan), index=table.index)
    out["pair_index"] = np.arange(len(table))
    for column in ("query", "reference", "label", "score", "num_inliers"):
        out[column] = table[column].to_numpy()
    out["method"], out["profile"] = method, IMPORTED_PROFILE
    return out


def check_name(name: str, option: str) -> str:
    """``name`` when it is a plain file-name component (it names folders and files), else a one-sentence refusal."""
    problem = name_problem(name) or ("is the output folder's own" if name == runs.RUNS else None)
    if problem:
        raise ScoreFileError(
            f"{option} {name!r} {problem}, and it names the output's files; give a plain name such as sp-sg-authors"
        )
    return name


def _check_joins(output_dir: Path, path: Path, sequence: str, digest: str) -> None:
    """Refuse an import into a folder that shows another sequence, or other pairs or labels."""
    shown = runs.current(output_dir).entries.values() if output_dir.is_dir() else []
    other_sequence = sorted({str(e.record.get("sequence")) for e in shown} - {sequence})
    if other_sequence:
        raise ScoreFileError(
            f"{output_dir} holds sequence {other_sequence[0]!r}, not {sequence!r}, and an output folder holds one "
            f"sequence; import {path} into another --output-dir, or give --sequence {other_sequence[0]} if it is that one"
        )
    other = [e.method for e in shown if (e.record.get("binding") or {}).get("pairs_digest") != digest]
    if other:
        raise ScoreFileError(
            f"{output_dir} holds {', '.join(other)}, scored on other pairs or labels than {path}; import it into "
            "another --output-dir"
        )


def import_scores(
    path: str | Path, sequence: str, method: str, output_dir: str | Path, image_root: str | Path | None = None
) -> dict[str, Any]:
    """Add a score file to ``output_dir`` as a run of ``method`` (beside the folder's other methods
    when they scored the same pairs and labels); returns its row of the results table and, under
    ``earlier``, the run of that name it now stands before (None when none). Given ``image_root``,
    the pairs' images are checked there first (``check_images``)."""
    path, output_dir = Path(path).resolve(), Path(output_dir)
    check_name(sequence, "--sequence")
    check_name(method, "--method")
    table, stated, kind = read_scores(path)
    if image_root is not None:
        check_images(table, sequence, Path(image_root).resolve())
    evaluate_scores(table["label"].to_numpy(), table["score"].to_numpy(), where=str(path))  # AP and MR defined
    digest = scoring.table_pairs_digest(table)
    binding = {
        "pairs_digest": digest,
        "images_digest": None,  # no images were read: the binding is the pairs and labels alone
    }
    runs.check_owned(output_dir)
    _check_joins(output_dir, path, sequence, digest)  # before any file
    earlier = next((e for e in reversed(runs.entries(output_dir)) if e.method == method), None)
    with runs.new_run(output_dir, "import") as building:
        run = _run_record(path, kind, stated, sequence, method, binding, building) | {"n_pairs": len(table)}
        run["imported"]["images_checked_under"] = None if image_root is None else str(Path(image_root).resolve())
        atomic_write_json(building / method / "run.json", run)
        atomic_write_csv(building / method / "pairs.csv", _pairs_csv(table, method))
    results = scoring.refresh_view(output_dir)
    row = results.set_index("method").loc[method].to_dict()
    return row | {"stated": stated, "run": runs.method_folder(output_dir, method).parent.name, "earlier": earlier}


def _run_record(
    path: Path, kind: str, stated: dict[str, Any], sequence: str, method: str, binding: dict[str, Any], run: Path
) -> dict[str, Any]:
    known = method in method_registry.method_names()
    return {
        "sequence": sequence,
        "image_root": "",  # no images were read
        "pairs": {"pairs_file": None, "pairs_sha256": None, "imported_from": str(path)},
        "binding": binding,
        "conf": {
            "method": method,
            "paper_name": f"{method_registry.paper_name(method) if known else method} (imported)",
            "profile": IMPORTED_PROFILE,
            "extractor": None,
            "matcher": None,
        },
        "seed": None,
        "package_version": __version__,
        "run_id": runs.run_id(run),
        "environment": {"device": "imported"},
        "this_run": {},
        "imported": {"file": str(path), "sha256": file_sha256(path), "format": kind, "stated": stated},
        "finished_at": runs.now(),
    }


def export_npy(output_dir: str | Path, method: str) -> tuple[Path, float]:
    """Write the method's run (the one the folder shows, or the run given) as the authors'
    ``<sequence>_<method>_<run id>.npy`` in the output folder's ``exports/``, and return it with the AP it
    states: their keys, with ``inliers`` one count a pair (as their multiprocess evaluation writes it) and
    no ``all_matches`` (the match coordinates are not in pairs.csv). A run never changes, so the export
    stays the run's it names."""
    output_dir = Path(output_dir)
    folder = method_outputs.method_dir(output_dir, method)
    table = scoring.load_pairs_table(folder.parent, method)
    run = method_outputs.read_run_json(folder.parent, method)
    run_id, sequence = str(runs.run_id(folder.parent)), str(run.get("sequence"))
    problem = name_problem(sequence)
    if problem:
        raise ScoreFileError(
            f"{folder / 'run.json'}: its sequence {sequence!r} {problem}, so it cannot name the export; run {method} "
            "again with a plain sequence name"
        )
    labels, scores = table["label"].to_numpy(dtype=np.int64), table["score"].to_numpy(dtype=np.float64)
    prob = scores / scores.max() if scores.max() > 0 else scores
    metrics = evaluate_scores(labels, prob, where=f"{folder / 'pairs.csv'}")
    curve = pr_curve(labels, prob)
    inliers = table["num_inliers"].to_numpy(dtype=np.float64)
    values = {
        "prob": prob,
        "qImages": table["query"].astype(str).tolist(),
        "rImages": table["reference"].astype(str).tolist(),
        "gt": labels.tolist(),
        "inliers": inliers.astype(np.int64) if np.isfinite(inliers).all() else scores,
        "precision": curve["precision"],
        "recall": curve["recall"],
        "TH": curve["thresholds"],
        "average_precision": metrics["ap"],
        "Max Recall": metrics["max_recall"],
    }
    target = runs.output_folder(output_dir) / "exports" / f"{sequence}_{method}_{run_id}.npy"
    target.parent.mkdir(exist_ok=True)
    temporary = target.with_name(f".{target.name}.tmp")
    with open(temporary, "wb") as handle:
        np.save(handle, np.array(values, dtype=object), allow_pickle=True)
    temporary.replace(target)
    return target, float(metrics["ap"])
