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
# The paper's supplementary comparison: inlier counting (F-RANSAC, the paper's GV) against the Doppelgangers classifier, AP and MR on the **test** split of a place-disjoint split (no place in both train and test). The classifier sees the 10-channel input built from the run's cached matches. The official checkpoint is used when present; the classifier trained here on the train split (same architecture, focal loss, Adam) is shown either way, named by its weights file. Rows labelled *paper* are the GV-Bench paper's published values on its own sequences, for reference only.

# %% tags=["parameters"]
params_file = "../params/sample.yaml"  # runs `method` when results_dir lacks its pairs.csv (None: run nothing)
results_dir = "../outputs/sample"  # the run folder holding <method>/pairs.csv and its match store
method = "sift-nn"  # whose cached matches every verifier re-scores
profile = None  # profile of that run when params_file must make it; None: the params file's
cache_dir = None  # feature cache of the run; None: <results_dir>/../cache
output_dir = "../outputs/sample/verifiers"  # verifiers.csv, weights, figures
# Place-disjoint split (frame ranges with a gap); tolerance = the largest frame offset of a true pair.
train_fraction = 0.4
gap_frames = 8
tolerance = 4
# In-domain Doppelgangers training (tiny by default so the notebook runs in seconds on a CPU).
size = 64
epochs = 1
max_train_pairs = 32
n_resamples = 1000  # query-bootstrap resamples for the 95% CIs

# %%
from pathlib import Path
import json
import matplotlib.pyplot as plt
import pandas as pd
from IPython.display import Markdown, display
from gvbench_nb import analysis, analysis_plots, plots, verifiers

results_dir = str(Path(results_dir).resolve())  # relative to this notebook, not to the params file
if params_file:
    verifiers.ensure_method_results(params_file, method, output_dir=results_dir, profile=profile)
figures = Path(output_dir)
overrides = {"doppelgangers-in-domain": {"size": size, "epochs": epochs, "max_train_pairs": max_train_pairs}}
bench = verifiers.open_bench(results_dir, method, output_dir, cache_dir, overrides=overrides,
                             train_fraction=train_fraction, gap_frames=gap_frames, tolerance=tolerance)
print(f"matches: {bench.cached.label}; split: {bench.split_conf}")
verifiers.split_summary(bench.pairs, bench.pairs["split"])

# %%
names = [verifiers.PAPER_VERIFIER, "doppelgangers", "doppelgangers-in-domain"]
results, tables, boot = bench.evaluate(names, "test", n_resamples)
official = results.set_index("verifier").loc["doppelgangers"]
if official["status"] != "ok":
    print(f"OFFICIAL CHECKPOINT ABSENT - {official['status']}\n"
          "Showing the in-domain-trained classifier instead (weights named below).")
info = bench.weights_info["doppelgangers-in-domain"]
print(f"in-domain weights: {info['weights']} ({'reused' if info.get('reused') else 'trained now'}); "
      f"{info['n_train_pairs']} train pairs ({info['n_train_positives']} true), "
      f"training {info['train_seconds']:.0f} s on {info['torch_threads']} thread(s), inputs {info['input_seconds']:.0f} s")
pd.DataFrame(info["history"], index=pd.RangeIndex(1, len(info["history"]["loss"]) + 1, name="epoch"))

# %%
paper = analysis.load_paper_table()
comparison = verifiers.doppelgangers_comparison(results, paper, bench.cached.sequence)
comparison.to_csv(figures / "doppelgangers_vs_gv.csv", index=False)
print(f"AP / MR in % (ours: {bench.cached.label}, test split, 95% CI from {n_resamples} query resamples; "
      "paper: as published, other sequences)")
shown = comparison.copy()
for metric in ("ap", "max_recall"):
    shown[metric] = (100 * shown[metric]).round(1)
shown.pivot_table(index=["source", "verifier"], columns="sequence", values=["ap", "max_recall"], sort=False)

# %%
verifiers.verifier_table(results)

# %%
figure = plots.pr_curves(tables, title=f"{bench.cached.label}, test split: GV vs Doppelgangers")
plots.save(figure, figures / "doppelgangers_vs_gv_pr.png"); plt.show()
print("verifiers.csv:", verifiers.write_results(results, output_dir))
