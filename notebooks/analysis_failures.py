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
# False positives: the highest-scoring false pairs; false negatives: the lowest-scoring
# true pairs, drawn with inlier matches green and outliers red (from the match store and
# the feature cache). Offsets are the ground-truth distance of a pair: frames |i - j|,
# and metres/degrees where the sequence has `poses.csv`. False positives just outside
# the ground-truth threshold are the label ambiguity the paper discusses.

# %%
from typing import Optional

import matplotlib.pyplot as plt
import pandas as pd
from IPython.display import Markdown, display

from gvbench_nb import notebook
from gvbench_nb.evaluation import plots, run_tables
from gvbench_nb.studies import failures

# %% tags=["parameters"]
output_dirs: list = ["../outputs/sample"]  # sequence output folders holding results.csv
# params files whose output folders must hold ensure_methods' results ([]: no check)
params_files: list = ["../params/sample.yaml"]
ensure_methods: list = ["sift-nn"]
# True: run ensure_methods where their pairs.csv is missing; False: an error naming
# the command that makes them
compute_missing: bool = False
output_dir: str = "../outputs/sample/analysis"  # figures (PNG) and tables are written here
k: int = 3  # pairs drawn a method and kind
near_low: int = 3  # false positives this many frames from the query or more ...
near_high: int = 5  # ... up to this many are 'just outside' the ground-truth threshold
near_top_k: int = 20  # how many top false positives are checked for near misses
cache_dir: Optional[str] = None  # feature and match cache; None: the one the run recorded (run.json)

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
runs, near_misses = [], []
for folder in output_dirs:
    measured = run_tables.measured_methods(folder)
    if not measured:  # imported scores only: no matches to draw
        continue
    tables = run_tables.load_pairs_tables(folder, measured)
    run = run_tables.load_run(folder, next(iter(tables)))
    sequence, image_root = run["sequence"], run["image_root"]
    failed = failures.failures_table(tables, k, image_root)
    runs.append((folder, sequence, image_root, failed))
    for method, table in tables.items():
        offsets = failures.ground_truth_offsets(table, image_root)
        near = failures.near_miss_false_positives(table, offsets, near_top_k, low=near_low, high=near_high)
        near_misses.append({"sequence": sequence, "method": method, **near})
near_misses = pd.DataFrame(near_misses)
near_misses.to_csv(figures / "near_miss_false_positives.csv", index=False)

# %% [markdown]
# Each sequence's failures, `k` a method and kind, ranked: the pair, its label and
# score, its matches and its ground-truth offset. A false positive with a small offset
# is a near miss of the labels rather than of the verifier. `collapsed`: its inliers fall on fewer distinct query or reference keypoints than half their number (docs/protocol.md, Collapsed inliers).

# %%
for _, sequence, _, failed in runs:
    display(Markdown(f"## {sequence}"), notebook.table(failed, precision=1))

# %% [markdown]
# The same pairs drawn query left, reference right, inlier matches green and outliers
# red. Green lines on a false positive are matches that fit one epipolar geometry
# although the places differ; a false negative with few green lines is a true pair whose
# images the method found little to match in. Shown as JPEG; each figure's full-size PNG,
# `false_positives_<sequence>_<method>.png` or `false_negatives_...`, is in `output_dir`.

# %%
for folder, sequence, image_root, failed in runs:
    for (method, kind), rows in failed.groupby(["method", "kind"], sort=False):
        what = kind.replace("_", " ")
        figure = failures.failure_pairs(
            rows,
            folder,
            method,
            image_root,
            cache_dir,
            title=f"{sequence} / {method}: top {what}s",
        )
        plots.save(figure, figures / f"{kind}s_{sequence}_{method}.png")
        display(failures.jpeg_view(figure))
        plt.close(figure)

# %% [markdown]
# False positives `near_low` to `near_high` frames from the query among each method's
# top `near_top_k` (`near_share_in_top`), against their share among all false pairs
# (`near_share_all_false`): a share at the top well above the share among all false
# pairs means near misses crowd the top of the ranking.

# %%
display(notebook.table(near_misses, precision=2))
