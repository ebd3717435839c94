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
# Every verifier of `alternative_verifiers.ALTERNATIVE_VERIFIERS` scored from the same cached matches, on the
# **test** split: robust estimators (RANSAC, DEGENSAC-like USAC_DEFAULT, LO-RANSAC/GC
# USAC_ACCURATE, MAGSAC++), fundamental matrix or homography, raw or normalised inlier
# scores; SUE over the query's GV-ranked candidates; the Doppelgangers classifier; and a
# logistic regression over GV features fitted on the train split. 95% CIs resample
# queries (paired: every verifier sees the same resamples).

# %%
from typing import Optional

import matplotlib.pyplot as plt
import pandas as pd
from IPython.display import Markdown, display

from gvbench_nb import notebook
from gvbench_nb.evaluation import plots
from gvbench_nb.studies import alternative_verifiers, uncertainty, verifier_inputs

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
verifier_names: Optional[list] = None  # None: every verifier in alternative_verifiers.ALTERNATIVE_VERIFIERS

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
# AP and MR in % with their 95% intervals of every verifier on the test split, its
# status (why one could not run) and weights; also merged into `verifiers.csv`. The
# paper's GV is `gv-F-ransac-inliers`: compare every other row with it.

# %%
names = list(verifier_names or alternative_verifiers.ALTERNATIVE_VERIFIERS)
results, tables, boot = bench.evaluate(names, "test", n_resamples)
print("verifiers.csv:", alternative_verifiers.write_results(results, figures))
notebook.table(alternative_verifiers.verifier_table(results).reset_index())

# %% [markdown]
# The intervals drawn, one row a verifier that ran, sorted by MR: the dot is the
# estimate on all test queries, the bar its 95% interval. Rows whose bars overlap are
# not told apart by these queries.

# %%
ok = results[results["status"] == "ok"].sort_values("max_recall", ascending=False)
intervals = boot.intervals().set_index("method").loc[ok["verifier"]].reset_index()
figure = uncertainty.bootstrap_intervals(intervals, title=f"{bench.cached.label}, test split: verifiers (95% CI)")
plots.save(figure, figures / "verifiers_ci.png")
plt.show()

# %% [markdown]
# The verifier with the best MR (then AP) and its gain over the paper's GV, with the
# paired bootstrap 95% interval of that gain: an interval that includes 0 means the gain
# is not established on these queries.

# %%
best = alternative_verifiers.best_by(results, boot, "max_recall")
display(
    Markdown(
        f"**Best MR: `{best['winner']}`**, {100 * best['difference']:+.1f} points over "
        f"`{best['baseline']}` (paired bootstrap 95% CI of the difference "
        f"[{100 * best['difference_ci_low']:+.1f}, "
        f"{100 * best['difference_ci_high']:+.1f}]; "
        f"it beats the baseline in {best['winner_beats_baseline_share']:.0%} "
        "of the resamples)."
    )
)
best_ap = alternative_verifiers.best_by(results, boot, "ap")
print(
    f"best AP: {best_ap['winner']} ({100 * best_ap['difference']:+.1f} points over "
    f"{best_ap['baseline']}, 95% CI [{100 * best_ap['difference_ci_low']:+.1f}, "
    f"{100 * best_ap['difference_ci_high']:+.1f}])"
)

# %% [markdown]
# What the learned combination weighs: the logistic regression's coefficient of each
# standardised GV feature, fitted on the train split. A feature whose coefficient is
# largest in magnitude moves the combined score most for one standard deviation.

# %%
conf = bench.conf("learned_combination")
train = bench.used()["split"] == "train"
features = bench.combination_features(conf)
labels = bench.used().loc[train, "label"]
model = alternative_verifiers.fit_combination(features[train], labels, conf)
coefficients = model[-1].coef_[0]
notebook.table(
    pd.Series(coefficients, index=features.columns, name="coefficient")
    .sort_values()
    .rename_axis("feature")
    .reset_index()
)
