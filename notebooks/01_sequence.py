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
from typing import Optional, Union

import matplotlib.pyplot as plt
import pandas as pd

from gvbench_nb import notebook
from gvbench_nb.data import sequences
from gvbench_nb.evaluation import plots

# %% tags=["parameters"]
params_file: Optional[str] = None  # a params YAML; None: the repository's params/sample.yaml
# Each key of a params file (`papermill -f PARAMS.yaml` passes them all), replacing params_file's;
# None: params_file's. Relative paths are relative to params_file's folder, as in the file; without
# params_file, every key given (-f ANY.yaml): relative to the working folder (the notebook prints which).
sequence: Optional[str] = None
description: Optional[str] = None
pairs_builder: Optional[str] = None
builder_options: Optional[dict] = None
image_root: Optional[str] = None
pairs: Optional[str] = None
methods: Union[str, list, None] = None  # a list, or names separated by commas
profile: Optional[str] = None  # 'paper' or 'repository'
output_dir: Optional[str] = None
cache_dir: Optional[str] = None
limit: Optional[int] = None  # first N pairs only
seed: Optional[int] = None
device: Optional[str] = None  # 'auto' (cuda when present), 'cpu' or 'cuda'
verifier: Optional[dict] = None
allow_damaged_images: Optional[bool] = None  # true: run on images whose decoder warns (each listed in the record)

# %% [markdown]
# The sequence's counts: pair_table, true pairs (positives) and false ones, queries and
# images. Check that every query has candidates and most have a positive: a query
# without one contributes only false pair_table.

# %%
params, seq = notebook.load_sequence(params_file, **notebook.params_keys(globals()))
figures = Path(params["output_dir"])
pd.Series(sequences.summarize(seq), name=seq.name).to_frame()

# %% [markdown]
# How many true references each query has. A bar at 0 counts the queries whose
# candidates are all false: any pair of theirs a verifier accepts is a false loop
# closure.

# %%
pair_table = seq.to_frame()
seq.check_images()  # names the first missing image and its pair
figure = plots.positives_per_query(pair_table, title=f"{seq.name}: true references a query")
plots.save(figure, figures / "sequence_positives_per_query.png")
plt.show()

# %% [markdown]
# Two true pairs (the first ones) and two false pairs (the last ones), query left,
# reference right. True pairs show the same place under the query's conditions; false
# pairs are what verification must reject.

# %%
examples = pd.concat([pair_table[pair_table.label == 1].head(2), pair_table[pair_table.label == 0].tail(2)])
figure = plots.example_pairs(
    seq.image_root,
    examples,
    title=f"{seq.name}: example pairs (query | reference)",
)
plots.save(figure, figures / "sequence_examples.png")
plt.show()
