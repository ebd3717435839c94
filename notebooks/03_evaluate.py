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

# %% tags=["parameters"]
params_file = "../params/sample.yaml"
methods = None  # default: every method with results in output_dir
output_dir = None

# %%
from pathlib import Path
import matplotlib.pyplot as plt
import pandas as pd
from IPython.display import display
from gvbench_nb import config, pipeline, plots, sequences

# %%
params = config.load_params(params_file, output_dir=output_dir)
out = Path(params["output_dir"])
results = pipeline.evaluate(out, methods)
print(f"results table: {out / 'results.csv'}")
results

# %%
tables = {m: pipeline.load_pairs_table(out, m) for m in results["method"]}
figure = plots.pr_curves(tables, title=f"{params['sequence']}: precision-recall (dot: MR)")
plots.save(figure, out / "pr_curves.png"); plt.show()
