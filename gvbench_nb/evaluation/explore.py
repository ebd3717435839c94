"""One pair across methods, from what the runs wrote (``pairs.csv`` and the match stores):
which pair to look at, its score and the rank of that score among each method's scores.
``notebooks/explore_pairs.ipynb`` is thin over these functions and ``analysis.match_lines``.
"""

from __future__ import annotations

import importlib.util
import os
import sys
from collections.abc import Sequence as SequenceType
from pathlib import Path

import pandas as pd

from gvbench_nb import pipeline
from gvbench_nb.evaluation import analysis

PICKS = ("index", "false_positive", "false_negative")
VIEW_COLUMNS = [
    "method",
    "pair_index",
    "query",
    "reference",
    "label",
    "num_matches",
    "num_inliers",
    "score",
    "rank",
    "n_pairs",
    "max_false_score",
    "above_all_false",
]


def load_tables(
    output_dir: str | os.PathLike[str], methods: SequenceType[str] | None = None
) -> dict[str, pd.DataFrame]:
    """``pairs.csv`` of each method (default: every method with results in ``output_dir``)."""
    methods = list(methods) if methods else pipeline.methods_with_results(Path(output_dir))
    if not methods:
        raise pipeline.ResultsError(
            f"{output_dir} holds no method results (<method>/pairs.csv); run a method "
            "first (python -m gvbench_nb run PARAMS --methods NAME)"
        )
    return {method: pipeline.load_pairs_table(Path(output_dir), method) for method in methods}


def score_ranks(table: pd.DataFrame) -> pd.Series:
    """Rank of each pair's score among its method's scores: 1 is the highest, and a pair
    tied with others gets the best rank of its tie (1 + the pairs scoring strictly higher)."""
    return table["score"].rank(method="min", ascending=False).astype(int)


def choose_pair(
    tables: dict[str, pd.DataFrame],
    pick: str = "index",
    pair_index: int | None = None,
    pick_method: str | None = None,
    pick_rank: int = 1,
) -> int:
    """The ``pair_index`` to show: ``pair_index`` itself (``pick='index'``), or the
    ``pick_rank``-th top false positive (highest-scoring false pair) or false negative
    (lowest-scoring true pair) of ``pick_method`` (default: the first method)."""
    if pick not in PICKS:
        raise ValueError(f"pick must be one of {', '.join(PICKS)}, got {pick!r}")
    first = next(iter(tables.values()))
    if pick == "index":
        if pair_index is None or not 0 <= int(pair_index) < len(first):
            raise ValueError(
                f"pair_index must be a pair of the run, 0 to {len(first) - 1}, got {pair_index!r}; "
                "or set pick to 'false_positive' or 'false_negative'"
            )
        return int(pair_index)
    method = pick_method or next(iter(tables))
    if method not in tables:
        raise ValueError(
            f"pick_method {method!r} is not among the methods shown ({', '.join(tables)}); add it to methods"
        )
    ranked = (analysis.top_false_positives if pick == "false_positive" else analysis.top_false_negatives)(
        tables[method], int(pick_rank)
    )
    if len(ranked) < int(pick_rank):
        kind = "false" if pick == "false_positive" else "true"
        raise ValueError(f"{method} has {len(ranked)} {kind} pairs, fewer than pick_rank {pick_rank}; lower pick_rank")
    return int(ranked["pair_index"].iloc[int(pick_rank) - 1])


def pair_across_methods(tables: dict[str, pd.DataFrame], pair_index: int) -> pd.DataFrame:
    """One row a method for pair ``pair_index``: its counts, score (``num_inliers``), the
    rank of that score among the method's ``n_pairs`` scores, the method's highest false
    score and whether the pair scores above it (how a true pair counts toward MR)."""
    rows = []
    for method, table in tables.items():
        if not 0 <= pair_index < len(table):
            raise ValueError(
                f"pair_index {pair_index} is outside {method}'s {len(table)} pairs; pick 0 to {len(table) - 1}"
            )
        row = table.iloc[pair_index]
        false_scores = table.loc[table["label"] == 0, "score"]
        max_false = float(false_scores.max()) if len(false_scores) else float("-inf")
        rows.append(
            {
                "method": method,
                "pair_index": int(row["pair_index"]),
                "query": row["query"],
                "reference": row["reference"],
                "label": int(row["label"]),
                "num_matches": int(row["num_matches"]),
                "num_inliers": int(row["num_inliers"]),
                "score": row["score"],
                "rank": int(score_ranks(table).iloc[pair_index]),
                "n_pairs": len(table),
                "max_false_score": max_false,
                "above_all_false": bool(row["score"] > max_false),
            }
        )
    view = pd.DataFrame(rows, columns=VIEW_COLUMNS)
    if view[["query", "reference"]].drop_duplicates().shape[0] > 1:
        raise ValueError(
            f"pair {pair_index} is not the same pair in every method's pairs.csv "
            f"({', '.join(view['method'])}); show methods run on the same pairs"
        )
    return view


def batch_execution() -> bool:
    """Whether this kernel runs a notebook in batch (papermill, nbmake and nbconvert start
    it through nbclient, which passes an in-memory history file), not a live session."""
    if any(arg.startswith("--HistoryManager.hist_file=:memory:") for arg in sys.argv):
        return True
    try:
        from IPython import get_ipython
    except ImportError:
        return True
    shell = get_ipython()
    if shell is None or not hasattr(shell, "kernel"):
        return True  # plain Python or a terminal IPython: nothing to draw widgets in
    # papermill injects its parameters as a cell headed '# Parameters'
    return any(str(source).startswith("# Parameters") for source in shell.user_ns.get("In", []))


def use_widgets(controls: str = "auto") -> bool:
    """``controls``: 'widgets', 'none' or 'auto' (widgets when ipywidgets is installed and
    the kernel is a live session, not a batch run)."""
    if controls not in ("auto", "widgets", "none"):
        raise ValueError(f"controls must be 'auto', 'widgets' or 'none', got {controls!r}")
    if controls == "none":
        return False
    available = importlib.util.find_spec("ipywidgets") is not None
    if controls == "widgets" and not available:
        raise ValueError("controls='widgets' needs ipywidgets (pip install ipywidgets); or set controls='auto'")
    return available and (controls == "widgets" or not batch_execution())
