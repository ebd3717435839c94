"""What notebooks/analysis_failures.ipynb computes and draws: the worst false positives and negatives."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import matplotlib.pyplot as plt
import numpy as np
import pandas as pd

from gvbench_nb.data.sequences import frame_index
from gvbench_nb.evaluation import collapsed_inliers, plots
from gvbench_nb.protocol.images import read_image
from gvbench_nb.studies import verifier_inputs


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
        q, r = poses.index.get_indexer(table["query"]), poses.index.get_indexer(table["reference"])
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
    """Top false positives and false negatives of every method with their offsets, and the distinct
    keypoints among their inliers (``collapsed``: ``collapsed_inliers.RULE``)."""
    frames = []
    for method, table in tables.items():
        for kind, rows in (
            ("false_positive", top_false_positives(table, k)),
            ("false_negative", top_false_negatives(table, k)),
        ):
            rows = rows.assign(method=method, kind=kind, rank=np.arange(1, len(rows) + 1))
            rows = rows.assign(collapsed=collapsed_inliers.collapsed(rows))
            frames.append(rows.join(ground_truth_offsets(rows, image_root)))
    columns = ["method", "kind", "rank", "pair_index", "query", "reference", "label", "score", "num_matches"]
    columns += ["num_inliers", *collapsed_inliers.INLIER_KEYPOINT_COUNTS, "collapsed"]
    frame = pd.concat(frames, ignore_index=True)
    # reindex: a table without the inlier keypoint counts shows them as not measured
    return frame.reindex(columns=columns + [c for c in ("frame_offset", "distance_m", "heading_deg") if c in frame])


def near_miss_false_positives(
    table: pd.DataFrame,
    offsets: pd.DataFrame,
    top_k: int = 20,
    column: str = "frame_offset",
    low: float = 3,
    high: float = 5,
) -> dict[str, Any]:
    """How many of the ``top_k`` highest false pairs lie just outside the ground-truth threshold
    (``low <= offset <= high``), against that share among all false pairs."""
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


def failure_pairs(
    rows: pd.DataFrame,
    output_dir: str | os.PathLike[str],
    method: str,
    image_root: str | os.PathLike[str],
    cache_dir: str | os.PathLike[str] | None = None,
    title: str = "",
) -> plt.Figure:
    """Each pair of ``rows`` (a failures table) drawn with inlier matches green, outliers red."""
    figure, axes = plt.subplots(len(rows), 1, figsize=(10, 3.4 * max(len(rows), 1)), squeeze=False)
    cached = verifier_inputs.CachedMatches(output_dir, method, cache_dir)
    cached.match_missing(zip(rows["query"], rows["reference"]))  # what the cache lacks, in one line
    for axis, row in zip(axes[:, 0], rows.itertuples()):
        pair = cached.pair(row.query, row.reference)
        image0 = read_image(Path(image_root) / row.query)
        image1 = read_image(Path(image_root) / row.reference)
        plots.draw_matches(image0, image1, pair.points0, pair.points1, pair.inlier_mask, axis=axis)
        offsets = [f"{row.frame_offset:.0f} frames" if not pd.isna(getattr(row, "frame_offset", np.nan)) else ""]
        if hasattr(row, "distance_m"):
            offsets.append(f"{row.distance_m:.1f} m, {row.heading_deg:.0f} deg")
        kind = "false positive" if row.label == 0 else "false negative"
        axis.set_title(
            f"{kind} #{row.rank}: {row.query} | {row.reference}  score {row.score:g} inliers"
            f"{collapsed_inliers.inlier_keypoints_words(row)} of {row.num_matches} matches; "
            f"ground-truth offset {', '.join(o for o in offsets if o)}",
            fontsize=8,
        )
    cached.close()
    if title:
        figure.suptitle(title)
    figure.tight_layout()
    return figure


def jpeg_view(figure: plt.Figure, dpi: int = 80, quality: int = 80) -> Any:
    """The figure as a JPEG for a notebook's page: photographs drawn into a PNG take over a megabyte
    a figure, which makes a page of a dozen pairs too heavy to open (the PNG saved beside it is full size)."""
    import io

    from IPython.display import Image

    buffer = io.BytesIO()
    figure.savefig(buffer, format="jpeg", dpi=dpi, bbox_inches="tight", pil_kwargs={"quality": quality})
    return Image(data=buffer.getvalue(), format="jpeg")
