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
# AP and max recall at 100% precision (MR) of every method, profile and sequence, in %:
# one row a (method, profile). **Bold**: the best of its column. Published values (grey
# italics) stand only beside ours of the same protocol: *paper* (the GV-Bench paper's
# table) in the rows of the paper profile, *GV-Bench repository* (its README's table) in
# those of the repository profile. Then MR across sequences (the paper's Fig. 1).

# %%
from typing import Optional

import matplotlib.pyplot as plt
from IPython.display import Markdown, display

from gvbench_nb import notebook
from gvbench_nb.evaluation import plots, run_tables
from gvbench_nb.studies import results_table, runtime_vs_mr

# %% tags=["parameters"]
output_dirs: list = ["../outputs/sample"]  # sequence output folders holding results.csv
# params files whose output folders must hold ensure_methods' results ([]: no check)
params_files: list = ["../params/sample.yaml"]
ensure_methods: list = ["sift-nn"]
# True: run ensure_methods where their pairs.csv is missing; False: an error naming
# the command that makes them
compute_missing: bool = False
output_dir: str = "../outputs/sample/analysis"  # figures (PNG) and tables are written here
# a paper_table.csv of your own; None: the one shipped in gvbench_nb/reference_values
paper_table: Optional[str] = None

# %%
notebook.check_parameters(globals())  # papermill's -p passes text: a list is given with -y
output_dirs, results, figures = notebook.load_results(
    output_dirs,
    output_dir,
    params_files,
    ensure_methods,
    compute_missing=compute_missing,
)

# %% [markdown]
# Ours beside the published values of the same protocol, in %, also written to
# `results_with_paper.csv`. Read across a row for one method on every sequence, down a
# column for the best method of a sequence and metric.

# %%
paper = results_table.load_paper_table(paper_table)
repository = results_table.load_repository_table()
joined = results_table.join_paper_table(results, paper, repository)
wide = results_table.results_table(joined)
joined.to_csv(figures / "results_with_paper.csv", index=False)
results_table.style_results_table(wide)

# %% [markdown]
# For context, the published tables (GV-Bench official sequences; values as published)
# for the methods we ran: the paper's (hloc chain) and the GV-Bench repository's (its
# current code). Each is comparable with ours only under its own profile, on the same
# sequence and pairs, and not with the other.

# %%
ran = results["method"].unique()
for table, source in ((paper, run_tables.PAPER_LABEL), (repository, run_tables.REPOSITORY_LABEL)):
    if len(table) and table["method"].isin(ran).any():
        display(Markdown(f"**{source}**"))
        published = results_table.paper_reference_table(table, ran, source=source)
        display(results_table.style_results_table(published))
    else:
        print(f"no {source} values for these methods")

# %% [markdown]
# Seconds per pair (extraction, matching and verification together) and FPS = 1 /
# seconds per pair of every run, with the device it ran on: compare speeds only between
# runs on the same device.

# %%
runtime = runtime_vs_mr.runtime_table(results)
notebook.table(runtime[["sequence", "profile", "method", "device", "seconds_per_pair", "fps"]])

# %% [markdown]
# MR of every (method, profile) on each sequence: ours, and the published value where
# the paper or the GV-Bench repository reports that method, sequence and profile (a
# radar with three sequences or more, bars otherwise). Look for the methods whose MR
# changes most from one sequence to another.

# %%
figure = results_table.max_recall_radar(joined)
plots.save(figure, figures / "max_recall_radar.png")
plt.show()
