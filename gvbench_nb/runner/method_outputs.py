"""A method's results: where they are read (its current run's folder), the columns of its per-pair
table, and the error when there are none."""

from __future__ import annotations

import os
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
    """Where a method's results are read or written: its folder in a run, its current run's in an output folder."""
    from gvbench_nb.runner import runs

    return runs.method_folder(output_dir, method)


def read_run_json(output_dir: str | os.PathLike[str], method: str) -> dict[str, Any]:
    """A method's record (its ``run.json``) as ``runs`` reads it; ``ResultsError`` when there is none."""
    from gvbench_nb.runner import runs

    record = runs.record(output_dir, method)
    if not isinstance(record, dict):
        raise ResultsError(
            f"{method_dir(Path(output_dir), method) / 'run.json'} is missing: run {method!r} on that sequence first"
        )
    return record


class ResultsError(GVBenchError, FileNotFoundError):
    """An output folder holds no results of a method, or none at all."""
