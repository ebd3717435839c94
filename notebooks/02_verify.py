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
# Extract (cached), match, fit F with RANSAC; writes `<method>/pairs.csv` and its figure in the run (on its
# own: a run of its own, `<output_dir>/runs/<id>/`, finished by the last cell).

# %%
from typing import Optional, Union

import matplotlib.pyplot as plt

from gvbench_nb import notebook
from gvbench_nb.evaluation import plots
from gvbench_nb.runner import method_runs, runs

# %% tags=["parameters"]
params_file: Optional[str] = None  # a params YAML; None: the repository's params/sample.yaml
method: str = "sift-nn"  # a name from `python -m gvbench_nb methods`
jobs: Optional[int] = None  # images, then pairs, processed at once; None: $GVBENCH_JOBS, else every core
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
# Run the method on every pair and write its table; the first rows follow. Each row is
# one pair: its label, the matches found, the RANSAC inliers (the score) and the seconds
# each stage took.

# %%
params, seq = notebook.load_sequence(params_file, **notebook.params_keys(globals()))
run = notebook.start_run(params, "02_verify")
table = method_runs.run_method_of_params({**params, "output_dir": str(run)}, seq, method, jobs=jobs)
print(
    f"{method} ({params['profile']}) on {seq.name}: {len(table)} pairs -> {method}/pairs.csv of run {runs.run_id(run)}"
)
table.head()

# %% [markdown]
# Matches and inliers of false (label 0) and true (label 1) pairs. Verification works
# when true pairs have many more inliers than false ones: compare the two columns'
# quartiles.

# %%
notebook.quartiles_by_label(table)

# %% [markdown]
# The inlier counts of true and false pairs as histograms. Where the two overlap no
# threshold separates them; MR counts the true pairs that score above every false pair.

# %%
figure = plots.inlier_histogram(table, title=f"{method} on {seq.name}")
plots.save(figure, run / f"inliers_{method}.png")
plt.show()
run = notebook.finish_run(params, run)
