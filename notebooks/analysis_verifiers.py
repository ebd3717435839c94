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
# # Verifiers beyond inlier counting
# Every verifier of `verifiers.VERIFIERS` scored from the same cached matches, on the **test** split: robust estimators (RANSAC, DEGENSAC-like USAC_DEFAULT, LO-RANSAC/GC USAC_ACCURATE, MAGSAC++), fundamental matrix or homography, raw or normalised inlier scores; SUE over the query's GV-ranked candidates; the Doppelgangers classifier; and a logistic regression over GV features fitted on the train split. 95% CIs resample queries (paired: every verifier sees the same resamples).

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
verifier_names = None  # None: every verifier in verifiers.VERIFIERS

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
names = list(verifier_names or verifiers.VERIFIERS)
results, tables, boot = bench.evaluate(names, "test", n_resamples)
print("verifiers.csv:", verifiers.write_results(results, output_dir))
verifiers.verifier_table(results)

# %%
ok = results[results["status"] == "ok"].sort_values("max_recall", ascending=False)
intervals = boot.intervals().set_index("method").loc[ok["verifier"]].reset_index()
figure = analysis_plots.bootstrap_intervals(intervals, title=f"{bench.cached.label}, test split: verifiers (95% CI)")
plots.save(figure, figures / "verifiers_ci.png"); plt.show()

# %%
best = verifiers.best_by(results, boot, "max_recall")
display(Markdown(
    f"**Best MR: `{best['winner']}`**, {100 * best['difference']:+.1f} points over `{best['baseline']}` "
    f"(paired bootstrap 95% CI of the difference [{100 * best['difference_ci_low']:+.1f}, "
    f"{100 * best['difference_ci_high']:+.1f}]; it beats the baseline in {best['winner_beats_baseline_share']:.0%} "
    "of the resamples)."))
best_ap = verifiers.best_by(results, boot, "ap")
print(f"best AP: {best_ap['winner']} ({100 * best_ap['difference']:+.1f} points over {best_ap['baseline']}, "
      f"95% CI [{100 * best_ap['difference_ci_low']:+.1f}, {100 * best_ap['difference_ci_high']:+.1f}])")

# %%
# What the learned combination weighs (standardised features, fitted on the train split).
conf = bench.conf("learned_combination")
train = bench.used()["split"] == "train"
features = bench.combination_features(conf)
model = verifiers.fit_combination(features[train], bench.used().loc[train, "label"], conf)
pd.Series(model[-1].coef_[0], index=features.columns, name="coefficient").sort_values()
