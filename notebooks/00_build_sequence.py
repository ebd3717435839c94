# ---
# jupyter:
#   jupytext:
#     formats: ipynb,py:percent
#     text_representation:
#       extension: .py
#       format_name: percent
#       format_version: '1.3'
#       jupytext_version: 1.19.6
#   kernelspec:
#     display_name: Python 3
#     language: python
#     name: python3
# ---

# %% [markdown]
# # 00 - Build a sequence the GV-Bench way
# Top-N retrieval by a global descriptor, labels by a ground-truth rule: writes the pair
# file and its card (`<stem>.card.json`, `.card.md`, `.candidates.csv`).

# %%
from pathlib import Path
from typing import Optional

import matplotlib.pyplot as plt
import pandas as pd
from IPython.display import Markdown, display

from gvbench_nb import notebook
from gvbench_nb.evaluation import plots
from gvbench_nb.runner import sequence_build
from gvbench_nb.studies import build_sequence as build_study

# %% tags=["parameters"]
# a params YAML with pairs_builder: retrieval
params_file: str = "../params/sample_retrieval.yaml"
descriptor: Optional[str] = None  # 'vlad', 'bow' or 'netvlad'; default: the params'
top_n: Optional[int] = None  # candidates a query; default: the params'
# recall@k figure, each with the params' descriptor_options (netvlad: weights, slow)
compare_descriptors: list = ["vlad", "bow"]
strip_count: int = 4  # queries shown with their top candidates
output_dir: Optional[str] = None  # figures go here; default: the params file's output_dir

# %% [markdown]
# The card of the pair file just built: its queries, pairs and positives (true loop
# closures), and the retrieval recall@k of the descriptor that chose the candidates.
# Look at "queries without a positive": verification cannot find a loop closure for
# them.

# %%
notebook.check_parameters(globals())  # papermill's -p passes text: a list is given with -y
params = sequence_build.load_build_params(params_file, descriptor=descriptor, top_n=top_n, output_dir=output_dir)
figures = Path(params["output_dir"])
card = sequence_build.build_sequence(params)
sequence_build.check_card(card["files"]["pairs"])  # the card's counts are the pair file's
display(Markdown(sequence_build.card_markdown(card)))

# %% [markdown]
# Recall@k of each descriptor in `compare_descriptors` on the same queries: the share of
# queries with a true reference among their top k candidates (table, then the curves).
# For the params' descriptor, the value at k = top N is the share of queries that get at
# least one true pair in the pair file.

# %%
curves = build_study.recall_curves(params, compare_descriptors)
display(curves.pivot(index="k", columns="descriptor", values="recall").round(3).T)
queries = curves.queries_evaluated.iloc[0]
figure = build_study.plot_recall_curves(curves, title=f"{card['sequence']}: retrieval recall@k ({queries} queries)")
plots.save(figure, figures / "build_recall_at_k.png")
plt.show()

# %% [markdown]
# A few queries (a rank-1 hit and a rank-1 miss first) with their top candidates, framed
# green when the ground truth calls the pair true and red when false. A red frame at
# rank 1 is a false candidate the descriptor scored above every true one.

# %%
candidates = pd.read_csv(card["files"]["candidates"])
shown = build_study.strip_queries(candidates, strip_count)
figure = build_study.candidate_strips(
    params["image_root"],
    candidates,
    shown,
    k=min(5, card["top_n"]),
    title=f"{card['sequence']}: top candidates by {card['descriptor']} (green true, red false)",
)
plots.save(figure, figures / "build_candidates.png")
plt.show()
