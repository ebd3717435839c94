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
# # Inlier distributions of true and false pairs
# Inliers divided by each method's largest count (as the paper's Figs. 6, 8, 9). The
# dashed line is the top false pair's score: only true pairs right of it count towards
# MR; true pairs with zero inliers are out of reach at any threshold.

# %%
import matplotlib.pyplot as plt
import pandas as pd

from gvbench_nb import notebook
from gvbench_nb.evaluation import plots, run_tables
from gvbench_nb.studies import inlier_histograms

# %% tags=["parameters"]
output_dirs: list = ["../outputs/sample"]  # sequence output folders holding results.csv
# params files whose output folders must hold ensure_methods' results ([]: no check)
params_files: list = ["../params/sample.yaml"]
ensure_methods: list = ["sift-nn"]
# True: run ensure_methods where their pairs.csv is missing; False: an error naming
# the command that makes them
compute_missing: bool = False
output_dir: str = "../outputs/sample/analysis"  # figures (PNG) and tables are written here

# %%
notebook.check_parameters(globals())  # papermill's -p passes text: a list is given with -y
output_dirs, results, figures = notebook.load_results(
    output_dirs,
    output_dir,
    params_files,
    ensure_methods,
    compute_missing=compute_missing,
)

# %%
# (sequence, {method: pairs table}) of every output folder
tables = [(notebook.sequence_of(results, folder), run_tables.load_pairs_tables(folder)) for folder in output_dirs]

# %% [markdown]
# One row a run: true and false pairs, the share of each with zero inliers (%), the top
# false pair's score (raw and normalised), and the share of true pairs above it (which
# is MR) or not, in %. Scores imported from elsewhere count too: the score ranks them.

# %%
shares = ["true_zero_inliers", "false_zero_inliers", "true_above_top_false", "true_in_overlap"]
notebook.table(
    pd.concat(
        [inlier_histograms.inlier_overlap_table(runs).assign(sequence=sequence) for sequence, runs in tables],
        ignore_index=True,
    ),
    percent=shares,
    labels=run_tables.run_labels(results),
)

# %% [markdown]
# Normalised inliers of true and false pairs, one panel a run. The shaded part right of
# the dashed line is where true pairs count towards MR; the wider the false pairs reach,
# the fewer true pairs are left there.

# %%
for sequence, runs in tables:
    counted, absent = inlier_histograms.with_inlier_counts(runs)
    for line in absent:
        print(line)
    if counted:
        figure = inlier_histograms.normalised_inlier_histograms(
            counted, title=f"{sequence}: normalised inliers, true vs false"
        )
        plots.save(figure, figures / f"normalised_inliers_{sequence}.png")
        plt.show()
