"""A method's results: where they are read (its current run's folder), the columns of its per-pair
table, and the error when there are none."""

from __future__ import annotations

import json
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


def read_run_json(output_dir: Path, method: str) -> dict[str, Any]:
    return json.loads((method_dir(output_dir, method) / "run.json").read_text(encoding="utf-8"))


class ResultsError(GVBenchError, FileNotFoundError):
    """An output folder holds no results of a method, or none at all."""
