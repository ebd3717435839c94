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
# # Runtime vs max recall
# Seconds per pair split by stage (extraction amortised over the pairs that share an image, matching, RANSAC verification) and FPS = 1 / seconds per pair against MR (the paper's Fig. 7). The device, profile and image size come from each run's `run.json`.

# %% tags=["parameters"]
output_dirs = ["../outputs/sample"]  # sequence output folders holding results.csv
params_files = ["../params/sample.yaml"]  # run these first where results are missing ([]: run nothing)
ensure_methods = ["sift-nn"]  # the methods ensure_results runs when their pairs.csv is missing
output_dir = "../outputs/sample/analysis"  # figures (PNG) and tables are written here
cache_dir = None  # feature cache (for image sizes); None: <output_dir>/../cache

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
runtime = analysis.runtime_table(results)
runtime

# %%
for sequence, group in runtime.groupby("sequence", sort=False):
    folder = results.loc[results["sequence"] == sequence, "output_dir"].iloc[0]
    caption = f"{sequence}: " + analysis.run_description(folder, list(group["method"]), cache_dir)
    print(caption)
    figure = analysis_plots.seconds_per_pair_stacked(group, caption=caption)
    plots.save(figure, figures / f"seconds_per_pair_{sequence}.png"); plt.show()
    figure = analysis_plots.fps_vs_max_recall(group, caption=caption)
    plots.save(figure, figures / f"fps_vs_max_recall_{sequence}.png"); plt.show()
