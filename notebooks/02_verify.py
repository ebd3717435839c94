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

# %%
from pathlib import Path

import matplotlib.pyplot as plt

from gvbench_nb import notebook
from gvbench_nb.evaluation import plots
from gvbench_nb.runner import method_outputs, method_runs

# %% tags=["parameters"]
params_file = "../params/sample.yaml"
method = "sift-nn"  # a name from `python -m gvbench_nb methods`
profile = None  # 'paper' or 'repository'; default: the params file's
limit = None
output_dir = None

# %% [markdown]
# Run the method on every pair and write its table; the first rows follow. Each row is
# one pair: its label, the matches found, the RANSAC inliers (the score) and the seconds
# each stage took.

# %%
params, sequence = notebook.load_sequence(params_file, limit=limit, output_dir=output_dir, profile=profile)
out = Path(params["output_dir"])
table = method_runs.run_method_of_params(params, sequence, method)
written = method_outputs.method_dir(out, method) / "pairs.csv"
run = f"{method} ({params['profile']}) on {sequence.name}"
print(f"{run}: {len(table)} pairs -> {written}")
table.head()

# %% [markdown]
# Matches and inliers of false (label 0) and true (label 1) pairs. Verification works
# when true pairs have many more inliers than false ones: compare the two columns'
# quartiles.

# %%
table.groupby("label")[["num_matches", "num_inliers"]].describe().transpose()

# %% [markdown]
# The inlier counts of true and false pairs as histograms. Where the two overlap no
# threshold separates them; MR counts the true pairs that score above every false pair.

# %%
figure = plots.inlier_histogram(table, title=f"{method} on {sequence.name}")
plots.save(figure, out / f"inliers_{method}.png")
plt.show()
