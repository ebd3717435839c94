"""A method's folder in an output folder: its name, the columns of its per-pair table, and the
marker that says a run is still making it.
"""

from __future__ import annotations

import datetime as _dt
import json
import os
import platform
from collections.abc import Iterable
from pathlib import Path
from typing import TYPE_CHECKING

from gvbench_nb import GVBenchError
from gvbench_nb.io_utils import atomic_write_json

if TYPE_CHECKING:
    pass


PAIRS_COLUMNS = [
    "pair_index",
    "query",
    "reference",
    "label",
    "method",
    "profile",
    "num_keypoints_query",
    "num_keypoints_reference",
    "num_matches",
    "num_matches_filtered",
    "num_inliers",
    "score",
    "extract_seconds",
    "match_seconds",
    "verify_seconds",
]


def method_dir(output_dir: Path, method: str) -> Path:
    return Path(output_dir) / method


UNFINISHED_MARKER = ".unfinished.json"  # in a method folder while a run is making its outputs


FINISHED_OUTPUTS = ("pairs.csv", "run.json")


class ResultsError(GVBenchError, FileNotFoundError):
    """An output folder holds no results, or a method's results are unfinished or partial."""


def replaced_profiles(output_dir: Path, methods: Iterable[str], profile: str) -> dict[str, str]:
    """Methods whose finished results in ``output_dir`` are of another profile than ``profile``
    (method -> that profile): a run of theirs there replaces those results."""
    replaced = {}
    for method in methods:
        try:
            run = json.loads((method_dir(output_dir, method) / "run.json").read_text(encoding="utf-8"))
            previous = run["conf"]["profile"]
        except (OSError, ValueError, KeyError, TypeError):
            continue
        if previous != profile:
            replaced[method] = previous
    return replaced


def claim_method_outputs(output_dir: Path, methods: Iterable[str], params_file: str | None = None) -> None:
    """Before any work of a run: remove each method's previous ``pairs.csv`` and
    ``run.json`` (and the folder's ``results.csv``) and mark its folder unfinished, so a
    run that fails at any point leaves nothing that looks like its result."""
    output_dir = Path(output_dir)
    (output_dir / "results.csv").unlink(missing_ok=True)
    for method in methods:
        folder = method_dir(output_dir, method)
        atomic_write_json(
            folder / UNFINISHED_MARKER,
            {
                "started_at": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
                "pid": os.getpid(),
                "host": platform.node(),
                "params_file": params_file,
            },
        )
        for stale in FINISHED_OUTPUTS:
            (folder / stale).unlink(missing_ok=True)


def unfinished_methods(output_dir: Path) -> dict[str, str]:
    """Method folders under ``output_dir`` whose results are not those of one finished
    run: method -> why (a run started and did not finish, or a file of the pair is missing)."""
    problems = {}
    for folder in sorted(p for p in Path(output_dir).iterdir() if p.is_dir()) if Path(output_dir).is_dir() else []:
        marker = folder / UNFINISHED_MARKER
        present = [name for name in FINISHED_OUTPUTS if (folder / name).is_file()]
        if marker.is_file():
            try:
                started = json.loads(marker.read_text(encoding="utf-8")).get("started_at", "?")
            except (OSError, ValueError):
                started = "?"
            problems[folder.name] = f"a run started at {started} has not finished (still running, failed or killed)"
        elif len(present) == 1:
            missing = next(name for name in FINISHED_OUTPUTS if name not in present)
            problems[folder.name] = f"{folder / missing} is missing beside {present[0]}"
    return problems


def check_results_finished(output_dir: Path) -> None:
    """Raise ``ResultsError`` naming each unfinished or partial method folder and what to do."""
    problems = unfinished_methods(output_dir)
    if problems:
        lines = "; ".join(f"{method}: {why}" for method, why in problems.items())
        raise ResultsError(
            f"{output_dir} holds unfinished results ({lines}); run those methods again "
            f"(python -m gvbench_nb run PARAMS --methods {','.join(problems)}) or delete their folders"
        )
