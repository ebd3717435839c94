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
# # 03 - Evaluate: AP, MR and PR curves of every method with results
# Reads only the runs' `pairs.csv`; writes `results.csv` and `pr_curves.png`.

# %%
from pathlib import Path
from typing import Optional

import matplotlib.pyplot as plt
from IPython.display import display

from gvbench_nb import notebook
from gvbench_nb.evaluation import plots
from gvbench_nb.runner import scoring

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
methods: Optional[list] = None  # the methods evaluated; None: every method with results in output_dir
profile: Optional[str] = None  # 'paper' or 'repository'
output_dir: Optional[str] = None
cache_dir: Optional[str] = None
limit: Optional[int] = None  # first N pairs only
seed: Optional[int] = None
device: Optional[str] = None  # 'auto' (cuda when present), 'cpu' or 'cuda'
verifier: Optional[dict] = None
allow_damaged_images: Optional[bool] = None  # true: run on images whose decoder warns (each listed in the record)

# %% [markdown]
# One row a method: pairs, positives, AP, max recall at 100 % precision (MR) and seconds
# a pair by stage, as written to `results.csv`. MR is the paper's headline metric: the
# share of true loop closures accepted before the first false one.

# %%
params = notebook.load_params(params_file, **notebook.params_keys(globals()))
out = Path(params["output_dir"])
results = scoring.evaluate(out, methods)
print(f"results table: {notebook.final_path(out / 'results.csv')}")
display(results)

# %% [markdown]
# Precision against recall as the acceptance threshold on the score falls, one curve a
# method; the dot on the top edge is its MR. A curve that stays at precision 1 longer
# accepts more loop closures without a false one.

# %%
tables = {m: scoring.load_pairs_table(out, m) for m in results["method"]}
figure = plots.pr_curves(tables, title=f"{params['sequence']}: precision-recall (dot: MR)")
plots.save(figure, out / "pr_curves.png")
plt.show()
