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
# Top-N retrieval by a global descriptor, labels by a ground-truth rule: writes the pair file and its card (`<stem>.card.json`, `.card.md`, `.candidates.csv`).

# %% tags=["parameters"]
params_file = "../params/sample_retrieval.yaml"  # a params YAML with pairs_builder: retrieval
descriptor = None  # 'vlad', 'bow' or 'netvlad'; default: the params'
top_n = None  # candidates a query; default: the params'
compare_descriptors = ["vlad", "bow"]  # recall@k figure, each with the params' descriptor_options (netvlad: weights, slow on CPU)
strip_count = 4  # queries shown with their top candidates
output_dir = None  # figures go here; default: the params file's output_dir

# %%
from pathlib import Path
import matplotlib.pyplot as plt
import pandas as pd
from IPython.display import Markdown, display
from gvbench_nb import build, plots

# %%
params = build.load_build_params(params_file, descriptor=descriptor, top_n=top_n, output_dir=output_dir)
figures = Path(params["output_dir"])
card = build.build_sequence(params)
build.check_card(card["files"]["pairs"])  # the card's counts are the pair file's
display(Markdown(build.card_markdown(card)))

# %%
curves = build.recall_curves(params, compare_descriptors)
display(curves.pivot(index="k", columns="descriptor", values="recall").round(3).T)
figure = build.plot_recall_curves(curves, title=f"{card['sequence']}: retrieval recall@k ({curves.queries_evaluated.iloc[0]} queries)")
plots.save(figure, figures / "build_recall_at_k.png"); plt.show()

# %%
candidates = pd.read_csv(card["files"]["candidates"])
shown = build.strip_queries(candidates, strip_count)
figure = build.candidate_strips(params["image_root"], candidates, shown, k=min(5, card["top_n"]),
                                title=f"{card['sequence']}: top candidates by {card['descriptor']} (green true, red false)")
plots.save(figure, figures / "build_candidates.png"); plt.show()
