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
# # Failures: top false positives and false negatives
# False positives: the highest-scoring false pairs; false negatives: the lowest-scoring true pairs, drawn with inlier matches green and outliers red (from the match store and the feature cache). Offsets are the ground-truth distance of a pair: frames |i - j|, and metres/degrees where the sequence has `poses.csv`. False positives just outside the ground-truth threshold are the label ambiguity the paper discusses.

# %% tags=["parameters"]
output_dirs = ["../outputs/sample"]  # sequence output folders holding results.csv
params_files = ["../params/sample.yaml"]  # run these first where results are missing ([]: run nothing)
ensure_methods = ["sift-nn"]  # the methods ensure_results runs when their pairs.csv is missing
output_dir = "../outputs/sample/analysis"  # figures (PNG) and tables are written here
k = 3  # pairs drawn a method and kind
near_low = 3  # false positives this many frames from the query or more ...
near_high = 5  # ... up to this many are 'just outside' the ground-truth threshold
near_top_k = 20  # how many top false positives are checked for near misses
cache_dir = None  # feature cache; None: <output_dir>/../cache

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
near_misses = []
for folder in output_dirs:
    tables = analysis.load_pairs_tables(folder)
    run = analysis.load_run(folder, next(iter(tables)))
    sequence, image_root = run["sequence"], run["image_root"]
    failures = analysis.failures_table(tables, k, image_root)
    display(Markdown(f"## {sequence}"), failures)
    for method, table in tables.items():
        offsets = analysis.ground_truth_offsets(table, image_root)
        near = analysis.near_miss_false_positives(table, offsets, near_top_k, low=near_low, high=near_high)
        near_misses.append({"sequence": sequence, "method": method, **near})
        for kind in ("false_positive", "false_negative"):
            rows = failures[(failures["method"] == method) & (failures["kind"] == kind)]
            figure = analysis_plots.failure_pairs(rows, folder, method, image_root, cache_dir,
                                                  title=f"{sequence} / {method}: top {kind.replace('_', ' ')}s")
            plots.save(figure, figures / f"{kind}s_{sequence}_{method}.png"); plt.show()
near_misses = pd.DataFrame(near_misses)
near_misses.to_csv(figures / "near_miss_false_positives.csv", index=False)
display(Markdown(f"## False positives {near_low}-{near_high} frames from the query "
                 f"(among each method's top {near_top_k}, vs all false pairs)"))
near_misses
