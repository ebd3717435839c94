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
# Inliers divided by each method's largest count (as the paper's Figs. 6, 8, 9). The dashed line is the top false pair's score: only true pairs right of it count towards MR; true pairs with zero inliers are out of reach at any threshold.

# %% tags=["parameters"]
output_dirs = ["../outputs/sample"]  # sequence output folders holding results.csv
params_files = ["../params/sample.yaml"]  # run these first where results are missing ([]: run nothing)
ensure_methods = ["sift-nn"]  # the methods ensure_results runs when their pairs.csv is missing
output_dir = "../outputs/sample/analysis"  # figures (PNG) and tables are written here

# %%
from pathlib import Path
import matplotlib.pyplot as plt
import pandas as pd
from IPython.display import Markdown, display
from gvbench_nb import analysis, analysis_plots, plots

# A single path given on the command line (papermill -p) arrives as a string.
output_dirs = [output_dirs] if isinstance(output_dirs, str) else list(output_dirs)
params_files = [params_files] if isinstance(params_files, str) else list(params_files or [])
for params_file in params_files:
    analysis.ensure_results(params_file, ensure_methods)
figures = Path(output_dir)
figures.mkdir(parents=True, exist_ok=True)
results = analysis.load_results(output_dirs)
print(f"{len(results)} results of {results['sequence'].nunique()} sequence(s): "
      f"{', '.join(results['sequence'].unique())}")

# %%
for folder in output_dirs:
    tables = analysis.load_pairs_tables(folder)
    sequence = results.loc[results["output_dir"] == str(Path(folder)), "sequence"].iloc[0]
    display(Markdown(f"## {sequence}"))
    display(analysis.inlier_overlap_table(tables))
    figure = analysis_plots.normalised_inlier_histograms(tables, title=f"{sequence}: normalised inliers, true vs false")
    plots.save(figure, figures / f"normalised_inliers_{sequence}.png"); plt.show()
