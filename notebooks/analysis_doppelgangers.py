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
# # GV vs Doppelgangers
# The paper's supplementary comparison: inlier counting (F-RANSAC, the paper's GV)
# against the Doppelgangers classifier, AP and MR on the **test** split of a
# place-disjoint split (no place in both train and test). The classifier sees the
# 10-channel input built from the run's cached matches. The official checkpoint is used
# when present; the classifier trained here on the train split (same architecture, focal
# loss, Adam) is shown either way, named by its weights file. Rows labelled *paper* are
# the GV-Bench paper's published values on its own sequences, for reference only.

# %%
from typing import Optional

import matplotlib.pyplot as plt
import pandas as pd

from gvbench_nb import notebook
from gvbench_nb.evaluation import plots, run_tables
from gvbench_nb.studies import alternative_verifiers, doppelgangers, results_table, verifier_inputs

# %% tags=["parameters"]
# with compute_missing, runs `method` when results_dir lacks its pairs.csv (None: never)
params_file: Optional[str] = "../params/sample.yaml"
# the run folder holding <method>/pairs.csv and run.json (which names the cache folder of its matches)
results_dir: str = "../outputs/sample"
method: str = "sift-nn"  # whose cached matches every verifier re-scores
profile: Optional[str] = None  # profile of that run when params_file must make it; None: the params'
# True: run `method` with params_file when its pairs.csv is missing; False: an error
# naming the command that makes it
compute_missing: bool = False
cache_dir: Optional[str] = None  # feature and match cache; None: the one the run recorded (run.json)
output_dir: str = "../outputs/sample/verifiers"  # verifiers.csv, weights, figures
# Place-disjoint split (frame ranges with a gap); tolerance = the largest frame offset
# of a true pair.
train_fraction: float = 0.4
gap_frames: int = 8
tolerance: int = 4
# In-domain Doppelgangers training (tiny by default: the notebook runs in seconds on
# a CPU).
size: int = 64
epochs: int = 1
max_train_pairs: int = 32
n_resamples: int = 1000  # query-bootstrap resamples for the 95% CIs

# %%
notebook.check_parameters(globals())  # papermill's -p passes text: a list is given with -y
bench = notebook.open_verifier_bench(
    results_dir,
    method,
    output_dir,
    params_file=params_file,
    profile=profile,
    cache_dir=cache_dir,
    compute_missing=compute_missing,
    classifier={"size": size, "epochs": epochs, "max_train_pairs": max_train_pairs},
    train_fraction=train_fraction,
    gap_frames=gap_frames,
    tolerance=tolerance,
)
figures = bench.output_dir  # output_dir, or where $GVBENCH_OUTPUTS moves it
print(f"matches: {bench.cached.label}; split: {bench.split_conf}")

# %% [markdown]
# The place-disjoint split: pairs, true pairs, queries and the frame range of the train
# and test parts, and of the pairs dropped in the gap between them. Train and test frame
# ranges must not overlap.

# %%
notebook.table(verifier_inputs.split_summary(bench.pairs, bench.pairs["split"]))

# %% [markdown]
# Score the test split with GV, the official classifier and the in-domain one (trained
# now, or reused when its weights exist), then its training loss an epoch. Over several
# epochs, a loss that does not fall means the in-domain classifier learned little.

# %%
names = [verifier_inputs.PAPER_VERIFIER, "doppelgangers", "doppelgangers-in-domain"]
results, tables, boot = bench.evaluate(names, "test", n_resamples)
official = results.set_index("verifier").loc["doppelgangers"]
if official["status"] != "ok":
    print(
        f"OFFICIAL CHECKPOINT ABSENT - {official['status']}\n"
        "Showing the in-domain-trained classifier instead (weights named below)."
    )
info = bench.weights_info["doppelgangers-in-domain"]
trained = "reused" if info.get("reused") else "trained now"
print(
    f"in-domain weights: {info['weights']} ({trained}); "
    f"{info['n_train_pairs']} train pairs ({info['n_train_positives']} true), "
    f"training {info['train_seconds']:.0f} s on {info['torch_threads']} thread(s), "
    f"inputs {info['input_seconds']:.0f} s"
)
epochs_run = pd.RangeIndex(1, len(info["history"]["loss"]) + 1, name="epoch")
notebook.table(pd.DataFrame(info["history"], index=epochs_run).reset_index())

# %% [markdown]
# AP and MR in % of each verifier: ours on this run's test split, beside the paper's
# SIFT+NN and Doppelgangers rows on its own sequences (also written to
# `doppelgangers_vs_gv.csv`). Compare rows within a source; across sources the sequences
# differ.

# %%
paper = results_table.load_paper_table()
comparison = doppelgangers.doppelgangers_comparison(results, paper, bench.cached.sequence)
comparison.to_csv(figures / "doppelgangers_vs_gv.csv", index=False)
print(
    f"AP / MR in % (ours: {bench.cached.label}, test split, 95% CI from "
    f"{n_resamples} query resamples; paper: as published, other sequences)"
)
shown = comparison.copy()
for metric in ("ap", "max_recall"):
    shown[metric] = (100 * shown[metric]).round(1)
notebook.table(
    shown.pivot_table(index=["source", "verifier"], columns="sequence", values=["ap", "max_recall"], sort=False)
    .rename(columns=run_tables.METRIC_HEADERS, level=0)
    .reset_index()
)

# %% [markdown]
# Ours again with the 95% intervals, the status of each verifier (why one could not run)
# and the weights it used. Overlapping intervals do not separate two verifiers.

# %%
notebook.table(alternative_verifiers.verifier_table(results).reset_index())

# %% [markdown]
# Precision-recall curves of the verifiers that ran, on the test split; the dot on the
# top edge is each one's MR. The curve that stays at precision 1 the longest accepts the
# most loop closures without a false one.

# %%
figure = plots.pr_curves(tables, title=f"{bench.cached.label}, test split: GV vs Doppelgangers")
plots.save(figure, figures / "doppelgangers_vs_gv_pr.png")
plt.show()
print("verifiers.csv:", alternative_verifiers.write_results(results, figures))
