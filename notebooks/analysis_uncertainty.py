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
# Queries are resampled with replacement (a pair goes with its query), the same
# resamples for every method, and AP and MR recomputed: 95% percentile intervals, and
# for every two methods the share of resamples where one beats the other. '>' marks a
# row method ranked above the column's: strictly better in at least 95% of resamples (the
# rule `compare` prints).

# %%
import matplotlib.pyplot as plt
import pandas as pd
from IPython.display import Markdown, display

from gvbench_nb import notebook
from gvbench_nb.evaluation import bootstrap, plots, run_tables
from gvbench_nb.studies import uncertainty

# %% tags=["parameters"]
output_dirs: list = ["../outputs/sample"]  # sequence output folders holding results.csv
# params files whose output folders must hold ensure_methods' results ([]: no check)
params_files: list = ["../params/sample.yaml"]
ensure_methods: list = ["sift-nn"]
# True: run ensure_methods where their pairs.csv is missing; False: an error naming
# the command that makes them
compute_missing: bool = False
output_dir: str = "../outputs/sample/analysis"  # figures (PNG) and tables are written here
n_resamples: int = 1000
seed: int = 0

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
boots = []  # (sequence, bootstrap) of every output folder
for folder in output_dirs:
    tables = run_tables.load_pairs_tables(folder)
    boots.append((notebook.sequence_of(results, folder), bootstrap.bootstrap(tables, n_resamples, seed)))
for sequence, boot in boots:
    print(f"{sequence}: {boot.n_queries} queries, {boot.n_pairs} pairs, {n_resamples} resamples")

# %% [markdown]
# AP and MR (%) of every method with its 95% interval (low, high) over the resamples (and
# how many resamples drew a true pair), also written to
# `bootstrap_intervals.csv` (as fractions).
# Two methods whose intervals overlap widely are not told apart by these queries.

# %%
intervals = pd.concat(
    [boot.intervals().assign(sequence=sequence) for sequence, boot in boots],
    ignore_index=True,
)
intervals.to_csv(figures / "bootstrap_intervals.csv", index=False)
labels = run_tables.run_labels(results)
display(notebook.table(intervals, percent=["estimate", "low", "high"], labels=labels))

# %% [markdown]
# The same intervals drawn, one row a method: the dot is the estimate on all queries,
# the bar its 95% interval.

# %%
for sequence, _ in boots:
    figure = uncertainty.bootstrap_intervals(
        intervals[intervals["sequence"] == sequence],
        title=f"{sequence}: 95% bootstrap intervals",
        labels=labels,
    )
    plots.save(figure, figures / f"bootstrap_intervals_{sequence}.png")
    plt.show()

# %% [markdown]
# For each metric, row method against column method: '>' ranked above (strictly better in
# at least 95% of resamples), '<' below, '~' a tie; then the shares of resamples behind
# each mark (first beats second, tied, second beats first), beside both values in %.

# %%
for sequence, boot in boots:
    if len(boot.methods) < 2:
        print(f"{sequence}: one method, no ranking to test")
        continue
    for metric in ("max_recall", "ap"):
        display(
            Markdown(f"**{sequence}, {run_tables.METRIC_HEADERS[metric]}**: row vs column"),
            boot.ranking_matrix(metric).rename(index=labels, columns=labels),
            notebook.table(boot.paired_shares(metric), percent=["first_value", "second_value"], labels=labels),
        )
