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
# # Results across sequences
# AP and max recall at 100% precision (MR) of every method, profile and sequence, in %: one row a (method, profile). **Bold**: the best of its column. Published values (grey italics) stand only beside ours of the same protocol: *paper* (the GV-Bench paper's table) in the rows of the paper profile, *GV-Bench repository* (its README's table) in those of the repository profile. Then MR across sequences (the paper's Fig. 1).

# %% tags=["parameters"]
output_dirs = ["../outputs/sample"]  # sequence output folders holding results.csv
params_files = ["../params/sample.yaml"]  # run these first where results are missing ([]: run nothing)
ensure_methods = ["sift-nn"]  # the methods ensure_results runs when their pairs.csv is missing
output_dir = "../outputs/sample/analysis"  # figures (PNG) and tables are written here
paper_table = None  # a paper_table.csv of your own; None: the one shipped in gvbench_nb/reference_values

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
paper = analysis.load_paper_table(paper_table)
repository = analysis.load_repository_table()
print(f"paper's table: {len(paper)} rows" if len(paper) else "paper's table not found: no paper values")
joined = analysis.join_paper_table(results, paper, repository)
wide = analysis.results_table(joined)
joined.to_csv(figures / "results_with_paper.csv", index=False)
analysis.style_results_table(wide)

# %% [markdown]
# For context, the published tables (GV-Bench official sequences; values as published) for the methods we ran: the paper's (hloc chain) and the GV-Bench repository's (its current code). Each is comparable with ours only under its own profile, on the same sequence and pairs, and not with the other.

# %%
for table, source in ((paper, analysis.PAPER_LABEL), (repository, analysis.REPOSITORY_LABEL)):
    if len(table) and table["method"].isin(results["method"]).any():
        display(Markdown(f"**{source}**"))
        display(analysis.style_results_table(analysis.paper_reference_table(table, results["method"].unique(),
                                                                            source=source)))
    else:
        print(f"no {source} values for these methods")

# %%
runtime = analysis.runtime_table(results)
runtime[["sequence", "profile", "method", "device", "seconds_per_pair", "fps"]]

# %%
figure = analysis_plots.max_recall_radar(
    joined, title="max recall at 100% precision (ours: solid, paper profile / dash-dot, repository profile; "
                  "published: dashed, paper / dotted, GV-Bench repository)")
plots.save(figure, figures / "max_recall_radar.png"); plt.show()
