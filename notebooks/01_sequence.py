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

# %% tags=["parameters"]
params_file = "../params/sample.yaml"  # a params YAML (paths inside are relative to it); a run passes its params.resolved.yaml
limit = None  # first N pairs only
output_dir = None  # default: the params file's output_dir

# %%
from pathlib import Path
import matplotlib.pyplot as plt
import pandas as pd
from IPython.display import display
from gvbench_nb import config, pipeline, plots, sequences

# %%
params = config.load_params(params_file, limit=limit, output_dir=output_dir)
sequence = config.prepare_sequence(params)
figures = Path(params["output_dir"])
summary = sequences.summarize(sequence)
pd.Series(summary, name=sequence.name).to_frame()

# %%
pairs = sequence.to_frame()
sequence.check_images()  # names the first missing image and its pair
figure = plots.positives_per_query(pairs, title=f"{sequence.name}: true references a query")
plots.save(figure, figures / "sequence_positives_per_query.png"); plt.show()

# %%
examples = pd.concat([pairs[pairs.label == 1].head(2), pairs[pairs.label == 0].tail(2)])
figure = plots.example_pairs(sequence.image_root, examples, title=f"{sequence.name}: example pairs (query | reference)")
plots.save(figure, figures / "sequence_examples.png"); plt.show()
