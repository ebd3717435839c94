"""A method's folder in an output folder: its name, the columns of its per-pair table, and the
check that its results are whole."""

from __future__ import annotations

import json
from collections.abc import Iterable
from pathlib import Path
from typing import Any

from gvbench_nb import GVBenchError

# Distinct keypoints among a pair's inliers: far fewer than num_inliers where a fit collapsed onto a
# few keypoints (docs/protocol.md, "Collapsed inliers").
INLIER_KEYPOINT_COUNTS = ("num_inlier_keypoints_query", "num_inlier_keypoints_reference")
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
    *INLIER_KEYPOINT_COUNTS,
    "score",
    "extract_seconds",
    "match_seconds",
    "verify_seconds",
]


def method_dir(output_dir: Path, method: str) -> Path:
    return Path(output_dir) / method


def read_run_json(output_dir: Path, method: str) -> dict[str, Any]:
    return json.loads((method_dir(output_dir, method) / "run.json").read_text(encoding="utf-8"))


FINISHED_OUTPUTS = ("pairs.csv", "run.json")


def result_files(method: str) -> list[str]:
    """A method's finished outputs as the folder's record names them (relative to the folder)."""
    return [f"{method}/{name}" for name in FINISHED_OUTPUTS]


class ResultsError(GVBenchError, FileNotFoundError):
    """An output folder holds no results, or a method's results are unfinished or partial."""


def replaced_profiles(output_dir: Path, methods: Iterable[str], profile: str) -> dict[str, str]:
    """Methods whose finished results in ``output_dir`` are of another profile than ``profile``
    (method -> that profile): a run of theirs there replaces those results."""
    replaced = {}
    for method in methods:
        try:
            previous = read_run_json(output_dir, method)["conf"]["profile"]
        except (OSError, ValueError, KeyError, TypeError):
            continue
        if previous != profile:
            replaced[method] = previous
    return replaced


def unfinished_methods(output_dir: Path) -> dict[str, str]:
    """Method folders under ``output_dir`` holding one of ``pairs.csv`` and ``run.json`` without
    the other: method -> which is missing."""
    problems = {}
    for folder in sorted(p for p in Path(output_dir).iterdir() if p.is_dir()) if Path(output_dir).is_dir() else []:
        present = [name for name in FINISHED_OUTPUTS if (folder / name).is_file()]
        if len(present) == 1:
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
