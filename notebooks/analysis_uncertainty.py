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
# # How sure are the rankings? A query bootstrap
# Queries are resampled with replacement (a pair goes with its query), the same resamples for every method, and AP and MR recomputed: 95% percentile intervals, and for every two methods the share of resamples where one beats the other. '>' marks a row method better than the column's in more than 97.5% of resamples.

# %% tags=["parameters"]
output_dirs = ["../outputs/sample"]  # sequence output folders holding results.csv
params_files = ["../params/sample.yaml"]  # run these first where results are missing ([]: run nothing)
ensure_methods = ["sift-nn"]  # the methods ensure_results runs when their pairs.csv is missing
output_dir = "../outputs/sample/analysis"  # figures (PNG) and tables are written here
n_resamples = 1000
seed = 0

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
all_intervals = []
for folder in output_dirs:
    tables = analysis.load_pairs_tables(folder)
    result = analysis.bootstrap(tables, n_resamples, seed)
    sequence = results.loc[results["output_dir"] == str(Path(folder)), "sequence"].iloc[0]
    intervals = result.intervals().assign(sequence=sequence)
    all_intervals.append(intervals)
    display(Markdown(f"## {sequence}: {result.n_queries} queries, {result.n_pairs} pairs, {n_resamples} resamples"))
    display(intervals)
    figure = analysis_plots.bootstrap_intervals(intervals, title=f"{sequence}: 95% bootstrap intervals")
    plots.save(figure, figures / f"bootstrap_intervals_{sequence}.png"); plt.show()
    for metric in ("max_recall", "ap"):
        if len(result.methods) > 1:
            display(Markdown(f"**{metric}**: row vs column ('>' significantly better, '<' worse, '~' not significant)"),
                    result.ranking_matrix(metric), result.pairwise(metric))
        else:
            print("one method: no ranking to test")
pd.concat(all_intervals).to_csv(figures / "bootstrap_intervals.csv", index=False)
