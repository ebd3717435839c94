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

import matplotlib.pyplot as plt
from IPython.display import display

from gvbench_nb.evaluation import plots
from gvbench_nb.runner import config, scoring

# %% tags=["parameters"]
params_file = "../params/sample.yaml"
methods = None  # default: every method with results in output_dir
output_dir = None

# %% [markdown]
# One row a method: pairs, positives, AP, max recall at 100 % precision (MR) and seconds
# a pair by stage, as written to `results.csv`. MR is the paper's headline metric: the
# share of true loop closures accepted before the first false one.

# %%
params = config.load_params(params_file, output_dir=output_dir)
out = Path(params["output_dir"])
results = scoring.evaluate(out, methods)
print(f"results table: {out / 'results.csv'}")
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
