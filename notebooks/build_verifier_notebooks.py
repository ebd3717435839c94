"""Write the verifier notebooks (GV vs Doppelgangers; every verifier side by side).

Thin like the others: a ``parameters`` cell, then calls into ``gvbench_nb.verification.verifiers``.
Every score comes from a finished run's CACHED matches (nothing is re-matched); with
the defaults the notebooks first run sift-nn on the embedded sample when its
``pairs.csv`` is missing, and train a tiny classifier, so they work on a fresh clone.
Rewrite them with:
    python notebooks/build_verifier_notebooks.py
"""

from __future__ import annotations



from build_notebooks import write_notebooks  # same folder: run this file as a script


PARAMETERS = """\
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
n_resamples = 1000  # query-bootstrap resamples for the 95% CIs"""

SETUP = """\
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
verifiers.split_summary(bench.pairs, bench.pairs["split"])"""

NOTEBOOKS: dict[str, list[tuple[str, str]]] = {
    "analysis_doppelgangers.ipynb": [
        ("md", "# GV vs Doppelgangers\nThe paper's supplementary comparison: inlier counting (F-RANSAC, the "
               "paper's GV) against the Doppelgangers classifier, AP and MR on the **test** split of a "
               "place-disjoint split (no place in both train and test). The classifier sees the 10-channel "
               "input built from the run's cached matches. The official checkpoint is used when present; the "
               "classifier trained here on the train split (same architecture, focal loss, Adam) is shown "
               "either way, named by its weights file. Rows labelled *paper* are the GV-Bench paper's "
               "published values on its own sequences, for reference only."),
        ("params", PARAMETERS),
        ("code", SETUP),
        ("code", """\
names = [verifiers.PAPER_VERIFIER, "doppelgangers", "doppelgangers-in-domain"]
results, tables, boot = bench.evaluate(names, "test", n_resamples)
official = results.set_index("verifier").loc["doppelgangers"]
if official["status"] != "ok":
    print(f"OFFICIAL CHECKPOINT ABSENT - {official['status']}\\n"
          "Showing the in-domain-trained classifier instead (weights named below).")
info = bench.weights_info["doppelgangers-in-domain"]
print(f"in-domain weights: {info['weights']} ({'reused' if info.get('reused') else 'trained now'}); "
      f"{info['n_train_pairs']} train pairs ({info['n_train_positives']} true), "
      f"training {info['train_seconds']:.0f} s on {info['torch_threads']} thread(s), inputs {info['input_seconds']:.0f} s")
pd.DataFrame(info["history"], index=pd.RangeIndex(1, len(info["history"]["loss"]) + 1, name="epoch"))"""),
        ("code", """\
paper = analysis.load_paper_table()
comparison = verifiers.doppelgangers_comparison(results, paper, bench.cached.sequence)
comparison.to_csv(figures / "doppelgangers_vs_gv.csv", index=False)
print(f"AP / MR in % (ours: {bench.cached.label}, test split, 95% CI from {n_resamples} query resamples; "
      "paper: as published, other sequences)")
shown = comparison.copy()
for metric in ("ap", "max_recall"):
    shown[metric] = (100 * shown[metric]).round(1)
shown.pivot_table(index=["source", "verifier"], columns="sequence", values=["ap", "max_recall"], sort=False)"""),
        ("code", """\
verifiers.verifier_table(results)"""),
        ("code", """\
figure = plots.pr_curves(tables, title=f"{bench.cached.label}, test split: GV vs Doppelgangers")
plots.save(figure, figures / "doppelgangers_vs_gv_pr.png"); plt.show()
print("verifiers.csv:", verifiers.write_results(results, output_dir))"""),
    ],
    "analysis_verifiers.ipynb": [
        ("md", "# Verifiers beyond inlier counting\nEvery verifier of `verifiers.VERIFIERS` scored from the "
               "same cached matches, on the **test** split: robust estimators (RANSAC, DEGENSAC-like "
               "USAC_DEFAULT, LO-RANSAC/GC USAC_ACCURATE, MAGSAC++), fundamental matrix or homography, raw or "
               "normalised inlier scores; SUE over the query's GV-ranked candidates; the Doppelgangers "
               "classifier; and a logistic regression over GV features fitted on the train split. 95% CIs "
               "resample queries (paired: every verifier sees the same resamples)."),
        ("params", PARAMETERS + """
verifier_names = None  # None: every verifier in verifiers.VERIFIERS"""),
        ("code", SETUP),
        ("code", """\
names = list(verifier_names or verifiers.VERIFIERS)
results, tables, boot = bench.evaluate(names, "test", n_resamples)
print("verifiers.csv:", verifiers.write_results(results, output_dir))
verifiers.verifier_table(results)"""),
        ("code", """\
ok = results[results["status"] == "ok"].sort_values("max_recall", ascending=False)
intervals = boot.intervals().set_index("method").loc[ok["verifier"]].reset_index()
figure = analysis_plots.bootstrap_intervals(intervals, title=f"{bench.cached.label}, test split: verifiers (95% CI)")
plots.save(figure, figures / "verifiers_ci.png"); plt.show()"""),
        ("code", """\
best = verifiers.best_by(results, boot, "max_recall")
display(Markdown(
    f"**Best MR: `{best['winner']}`**, {100 * best['difference']:+.1f} points over `{best['baseline']}` "
    f"(paired bootstrap 95% CI of the difference [{100 * best['difference_ci_low']:+.1f}, "
    f"{100 * best['difference_ci_high']:+.1f}]; it beats the baseline in {best['winner_beats_baseline_share']:.0%} "
    "of the resamples)."))
best_ap = verifiers.best_by(results, boot, "ap")
print(f"best AP: {best_ap['winner']} ({100 * best_ap['difference']:+.1f} points over {best_ap['baseline']}, "
      f"95% CI [{100 * best_ap['difference_ci_low']:+.1f}, {100 * best_ap['difference_ci_high']:+.1f}])")"""),
        ("code", """\
# What the learned combination weighs (standardised features, fitted on the train split).
conf = bench.conf("learned_combination")
train = bench.used()["split"] == "train"
features = bench.combination_features(conf)
model = verifiers.fit_combination(features[train], bench.used().loc[train, "label"], conf)
pd.Series(model[-1].coef_[0], index=features.columns, name="coefficient").sort_values()"""),
    ],
}


if __name__ == "__main__":
    write_notebooks(NOTEBOOKS)
