"""Collapsed inliers: a pair whose RANSAC inliers fall on few distinct keypoints, and the warning when
such pairs set a method's MR (docs/protocol.md, "Collapsed inliers").

Many matches of one image onto a single keypoint of the other fit any fundamental matrix whose
epipolar lines pass through that keypoint, so their inlier count says little about the geometry.
The protocol's score stays ``num_inliers``; this module only names the pairs where it misleads.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import pandas as pd

from gvbench_nb.runner.method_outputs import INLIER_KEYPOINT_COUNTS

# A pair collapses when its distinct query or reference keypoints among the inliers are fewer than
# this share of its inliers.
COLLAPSE_SHARE = 0.5
RULE = "distinct query or reference keypoints among its inliers fewer than half its inliers"


def distinct_inlier_keypoints(table: pd.DataFrame) -> pd.Series:
    """Per pair, min(distinct query, distinct reference keypoints among its inliers): inliers counted
    once per keypoint of the side they collapse on (NaN where the counts were not measured)."""
    return table.reindex(columns=list(INLIER_KEYPOINT_COUNTS)).min(axis=1, skipna=False)


def collapsed(table: pd.DataFrame) -> pd.Series:
    """Per pair, whether its inliers collapse (``RULE``); False where the counts were not measured."""
    return distinct_inlier_keypoints(table) < COLLAPSE_SHARE * table["num_inliers"]


def inlier_keypoints_words(row: Any) -> str:
    """' on Q query and R reference keypoints' of a table's row (itertuples), with ', collapsed,' where
    ``collapsed`` says so; '' where the counts were not measured. Said right after the inliers."""
    query, reference = (getattr(row, name, np.nan) for name in INLIER_KEYPOINT_COUNTS)
    if pd.isna(query) or pd.isna(reference):
        return ""
    marked = ", collapsed," if getattr(row, "collapsed", False) else ""
    return f" on {query:.0f} query and {reference:.0f} reference keypoints{marked}"


def mr_setting_pairs(table: pd.DataFrame) -> pd.DataFrame:
    """The false pairs scoring highest: MR is the share of true pairs scoring above them."""
    false = table[table["label"] == 0]
    return false[false["score"] == false["score"].max()]


def _pair_words(row: pd.Series) -> str:
    return f"false pair {int(row['pair_index'])} ({row['query']} | {row['reference']})"


def collapse_warning(method: str, table: pd.DataFrame) -> str | None:
    """One line when ``method``'s MR is set by collapsed pairs only (every false pair at the top score
    collapses), or when its table cannot tell; None otherwise, and for scores with no matches counted."""
    top = mr_setting_pairs(table)
    if not len(top) or top.reindex(columns=["num_matches"])["num_matches"].isna().all():
        return None  # imported scores: no matches here to count keypoints of
    first = top.iloc[0]
    tied = f" and {len(top) - 1} more false pairs tied with it" if len(top) > 1 else ""
    if distinct_inlier_keypoints(top).isna().any():
        return (
            f"{method}: MR is set by {_pair_words(first)}{tied}, but its pairs.csv does not count the distinct "
            "keypoints among the inliers, so whether they collapse is not checked; run the method again to count them"
        )
    if not collapsed(top).all():
        return None
    query, reference = (int(first[name]) for name in INLIER_KEYPOINT_COUNTS)
    both = " (all collapsed)" if len(top) > 1 else ""
    return (
        f"{method}: MR is set by {_pair_words(first)}{tied}{both}, whose {int(first['num_inliers'])} inliers fall on "
        f"{query} distinct query and {reference} distinct reference keypoints: a collapsed fit ({RULE}; "
        "docs/protocol.md, Collapsed inliers)"
    )


def collapse_warnings(tables: dict[str, pd.DataFrame]) -> list[str]:
    """``collapse_warning`` of every method that has one, in the order of ``tables``."""
    return [line for method, table in tables.items() if (line := collapse_warning(method, table)) is not None]
