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
# # 01 - What a sequence holds
# Counts, positives a query and example pairs of one sequence.

# %%
from pathlib import Path

import matplotlib.pyplot as plt
import pandas as pd

from gvbench_nb import notebook
from gvbench_nb.data import sequences
from gvbench_nb.evaluation import plots

# %% tags=["parameters"]
# a params YAML (paths inside are relative to it); a run passes its params.resolved.yaml
params_file = "../params/sample.yaml"
limit = None  # first N pairs only
output_dir = None  # default: the params file's output_dir

# %% [markdown]
# The sequence's counts: pairs, true pairs (positives) and false ones, queries and
# images. Check that every query has candidates and most have a positive: a query
# without one contributes only false pairs.

# %%
params, sequence = notebook.load_sequence(params_file, limit=limit, output_dir=output_dir)
figures = Path(params["output_dir"])
pd.Series(sequences.summarize(sequence), name=sequence.name).to_frame()

# %% [markdown]
# How many true references each query has. A bar at 0 counts the queries whose
# candidates are all false: any pair of theirs a verifier accepts is a false loop
# closure.

# %%
pairs = sequence.to_frame()
sequence.check_images()  # names the first missing image and its pair
figure = plots.positives_per_query(pairs, title=f"{sequence.name}: true references a query")
plots.save(figure, figures / "sequence_positives_per_query.png")
plt.show()

# %% [markdown]
# Two true pairs (the first ones) and two false pairs (the last ones), query left,
# reference right. True pairs show the same place under the query's conditions; false
# pairs are what verification must reject.

# %%
examples = pd.concat([pairs[pairs.label == 1].head(2), pairs[pairs.label == 0].tail(2)])
figure = plots.example_pairs(
    sequence.image_root,
    examples,
    title=f"{sequence.name}: example pairs (query | reference)",
)
plots.save(figure, figures / "sequence_examples.png")
plt.show()
