"""What notebooks/00_build_sequence.ipynb computes and draws beside the pair file it builds: recall@k
curves of the retrieval, the best experience per query, and strips of candidates."""

from __future__ import annotations

from collections.abc import Mapping
from collections.abc import Sequence as SequenceType
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from gvbench_nb.data import build_inputs, retrieval
from gvbench_nb.runner import sequence_build


def recall_curves(
    build_params: Mapping[str, Any], descriptors: SequenceType[str], progress: bool = True
) -> pd.DataFrame:
    """Retrieval recall@k (k = 1..top_n) of each descriptor, with the params' options, on the same
    queries and ground truth: descriptor, k, recall, queries_evaluated."""
    inputs = build_inputs.prepare_inputs(build_params)
    truth = sequence_build.ground_truth(inputs)
    max_k = min(inputs.options.top_n, truth.shape[1])
    rows = []
    for name in descriptors:
        reference, query = sequence_build.global_descriptors(inputs, name, inputs.descriptor_options(name), progress)
        ranked, _ = retrieval.retrieve_top_n(query, reference, max_k)
        recall = retrieval.retrieval_recall_at(range(1, max_k + 1), ranked, truth)
        rows += [(name, k, recall[f"recall@{k}"], recall["queries_evaluated"]) for k in range(1, max_k + 1)]
    return pd.DataFrame(rows, columns=["descriptor", "k", "recall", "queries_evaluated"])


def best_experience_table(candidates: pd.DataFrame, pairs_table: pd.DataFrame, score: str = "score") -> pd.DataFrame:
    """Per query (in candidate order), its best-scoring pair over every experience, a tie going to the
    better retrieval rank: query, experience, reference, rank, score, label."""
    scored = candidates.merge(pairs_table[["query", "reference", score]], on=["query", "reference"], how="left")
    if scored[score].isna().any():
        missing = scored[scored[score].isna()].iloc[0]
        raise build_inputs.BuildError(
            f"no {score!r} for candidate pair {missing['query']} {missing['reference']} in the pairs table; "
            "run the method on the built pair file first (without --limit)"
        )
    scored["order"] = pd.factorize(scored["query"])[0]
    best = scored.sort_values(["order", score], ascending=[True, False], kind="stable").drop_duplicates("query")
    return best[["query", "experience", "reference", "rank", score, "label"]].reset_index(drop=True)


def plot_recall_curves(curves: pd.DataFrame, title: str = "") -> Any:
    """Recall@k against k, one line a descriptor."""
    import matplotlib.pyplot as plt

    figure, axis = plt.subplots(figsize=(6, 3.8))
    for name, group in curves.groupby("descriptor", sort=False):
        axis.plot(
            group["k"], group["recall"], marker="o", markersize=3, label=f"{name} (R@1 {group['recall'].iloc[0]:.1%})"
        )
    axis.set(xlabel="k (candidates a query)", ylabel="recall@k", ylim=(0, 1.02), title=title or "retrieval recall@k")
    axis.grid(alpha=0.3)
    axis.legend(loc="lower right", fontsize=8)
    return figure


def candidate_strips(
    image_root: str | Path, candidates: pd.DataFrame, queries: SequenceType[str], k: int = 5, title: str = ""
) -> Any:
    """A row a query: the query image, then its top-k candidates framed green (true) or red (false)."""
    import matplotlib.pyplot as plt

    from gvbench_nb.protocol.images import read_image

    figure, axes = plt.subplots(len(queries), k + 1, figsize=(2.2 * (k + 1), 1.6 * len(queries)), squeeze=False)
    for axis_row, query in zip(axes, queries):
        ranked = candidates[candidates["query"] == query].sort_values("rank").head(k)
        axis_row[0].imshow(read_image(Path(image_root) / query))
        axis_row[0].set_title(f"query {query}", fontsize=7)
        for axis, (_, row) in zip(axis_row[1:], ranked.iterrows()):
            axis.imshow(read_image(Path(image_root) / row["reference"]))
            colour = "green" if row["label"] == 1 else "red"
            axis.set_title(
                f"#{row['rank'] + 1} {row['reference']}\nsim {row['similarity']:.3f}", fontsize=7, color=colour
            )
            for spine in axis.spines.values():
                spine.set(edgecolor=colour, linewidth=3)
        for axis in axis_row:
            axis.set(xticks=[], yticks=[])
    if title:
        figure.suptitle(title)
    figure.tight_layout()
    return figure


def strip_queries(candidates: pd.DataFrame, count: int = 4) -> list[str]:
    """Queries to show: a rank-1 hit and a rank-1 miss first when there are both, then
    evenly spaced others (deterministic)."""
    top = candidates[candidates["rank"] == 0]
    chosen: list[str] = []
    for label in (1, 0):
        found = top[top["label"] == label]["query"]
        if len(found) and len(chosen) < count:
            chosen.append(found.iloc[len(found) // 2])
    queries = list(dict.fromkeys(candidates["query"]))
    for index in np.linspace(0, len(queries) - 1, num=count).round().astype(int):
        if len(chosen) >= count:
            break
        if queries[index] not in chosen:
            chosen.append(queries[index])
    return chosen
