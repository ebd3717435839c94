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
# # 02 - Verify: one method on one sequence
# Extract (cached), match, fit F with RANSAC; writes `<output_dir>/<method>/pairs.csv`.

# %% tags=["parameters"]
params_file = "../params/sample.yaml"
method = "sift-nn"  # a name from `python -m gvbench_nb methods`
profile = None  # 'paper' or 'repository'; default: the params file's
limit = None
output_dir = None

# %%
from pathlib import Path
import matplotlib.pyplot as plt
import pandas as pd
from IPython.display import display
from gvbench_nb import config, pipeline, plots, sequences

# %%
params = config.load_params(params_file, limit=limit, output_dir=output_dir, profile=profile)
sequence = config.prepare_sequence(params)
table = pipeline.run_method(sequence, method, params["profile"], Path(params["output_dir"]), Path(params["cache_dir"]),
                            device=params["device"], seed=params["seed"])
print(f"{method} ({params['profile']}) on {sequence.name}: {len(table)} pairs -> {pipeline.method_dir(params['output_dir'], method) / 'pairs.csv'}")
table.head()

# %%
table.groupby("label")[["num_matches", "num_inliers"]].describe().T

# %%
figure = plots.inlier_histogram(table, title=f"{method} on {sequence.name}")
plots.save(figure, Path(params["output_dir"]) / f"inliers_{method}.png"); plt.show()
