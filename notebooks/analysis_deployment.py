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
# # Deployment: a threshold fixed before the place is seen
# MR is the recall at an oracle threshold, chosen per sequence with the labels in hand. A
# SLAM system fixes its inlier threshold first. Here each method's threshold of 100%
# precision on one sequence (the one MR is read at) is applied to every other: precision,
# recall and the false loops it accepts. Then, per query, GV re-ranks the candidates:
# recall@1 after GV, and the queries that would close a false loop.

# %%
from typing import Optional

import matplotlib.pyplot as plt
from IPython.display import Markdown, display

from gvbench_nb import notebook
from gvbench_nb.evaluation import plots, run_tables
from gvbench_nb.studies import deployment

# %% tags=["parameters"]
# sequence output folders holding results.csv (one a sequence); each calibrates every one
output_dirs: list = ["../outputs/sample"]
# params files whose output folders must hold ensure_methods' results ([]: no check)
params_files: list = ["../params/sample.yaml"]
ensure_methods: list = ["sift-nn"]
# True: run ensure_methods where their pairs.csv is missing; False: an error naming
# the command that makes them
compute_missing: bool = False
output_dir: str = "../outputs/sample/analysis"  # figures (PNG) and tables are written here
calibrations: Optional[list] = None  # sequences the thresholds are fixed on; None: every one

# %%
notebook.check_parameters(globals())  # papermill's -p passes text: a list is given with -y
output_dirs, results, figures = notebook.load_results(
    output_dirs,
    output_dir,
    params_files,
    ensure_methods,
    compute_missing=compute_missing,
)
inputs = deployment.DeploymentInputs(output_dirs)

# %% [markdown]
# One matrix a method: the threshold fixed on the row's sequence, applied to the column's.
# Each cell is precision / recall / false loops accepted ('-': nothing passes). The
# diagonal is MR (precision 1, no false loop); off it, a false loop is a wrecked map.
# Also written to `transfer.csv`.

# %%
transfer = deployment.transfer_table(inputs, calibrations)
transfer.to_csv(figures / "transfer.csv", index=False)
for method, profile in deployment.runs(transfer):
    display(Markdown(f"**{plots.run_label(method, profile)}**"), deployment.transfer_matrix(transfer, method, profile))

# %%
figure = deployment.transfer_figure(transfer)
plots.save(figure, figures / "threshold_transfer.png")
plt.show()

# %% [markdown]
# The loop-closure level: each query keeps its best-scoring candidate (ties keep the pair
# file's order). Recall@1 after GV: the share of queries with a true candidate whose best
# is true, in %; recall@1 of retrieval: the same for the first candidate, where the pair
# file keeps the retrieval order (a `retrieval`-built sequence; empty otherwise, as for
# rule-built sequences); true / false loops closed: queries whose best candidate passes
# the threshold fixed on the calibration sequence. Also written to `loop_closures.csv`.

# %%
loops = deployment.loop_closure_table(transfer, inputs)
loops.to_csv(figures / "loop_closures.csv", index=False)
notebook.table(loops, percent=deployment.LOOP_SHARES, labels=run_tables.run_labels(results))
