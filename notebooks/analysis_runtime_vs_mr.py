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
# # Runtime vs max recall
# Seconds per pair split by stage (extraction amortised over the pairs that share an
# image, matching, RANSAC verification) and FPS = 1 / seconds per pair against MR (the
# paper's Fig. 7). The device, profile and image size come from each run's `run.json`.

# %%
from typing import Optional

import matplotlib.pyplot as plt
from IPython.display import display

from gvbench_nb import notebook
from gvbench_nb.evaluation import plots
from gvbench_nb.studies import runtime_vs_mr

# %% tags=["parameters"]
output_dirs: list = ["../outputs/sample"]  # sequence output folders holding results.csv
# params files whose output folders must hold ensure_methods' results ([]: no check)
params_files: list = ["../params/sample.yaml"]
ensure_methods: list = ["sift-nn"]
# True: run ensure_methods where their pairs.csv is missing; False: an error naming
# the command that makes them
compute_missing: bool = False
output_dir: str = "../outputs/sample/analysis"  # figures (PNG) and tables are written here
cache_dir: Optional[str] = None  # feature cache (for image sizes); None: the one the run recorded (run.json)

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
# One row a run: seconds per pair by stage and in total, FPS, and its MR and AP (%). The
# stage columns add up to the seconds a pair. A method whose scores were imported has no
# seconds measured here and is named once, not drawn.

# %%
runtime = runtime_vs_mr.runtime_table(results)
for line in runtime_vs_mr.unmeasured_lines(results):
    print(line)
display(notebook.table(runtime))

# %% [markdown]
# Each sequence's runs described for the captions below: device, profile and the size of
# each traversal's images (read from each image folder's first image), then what each
# method resized them to.

# %%
captions = {}
for sequence, group in runtime.groupby("sequence", sort=False):
    folder = results.loc[results["sequence"] == sequence, "output_dir"].iloc[0]
    methods = list(group["method"])
    description = runtime_vs_mr.run_description(folder, methods, cache_dir)
    captions[sequence] = f"{sequence}: {description}"
    print(captions[sequence])

# %% [markdown]
# Seconds per pair of each run, one stacked bar a run split into extraction, matching
# and verification, total at its end. The longest segment is where a method spends its
# time.

# %%
for sequence, group in runtime.groupby("sequence", sort=False):
    figure = runtime_vs_mr.seconds_per_pair_stacked(group, caption=captions[sequence])
    plots.save(figure, figures / f"seconds_per_pair_{sequence}.png")
    plt.show()

# %% [markdown]
# FPS (log scale) against MR, one point a run: right is faster, up has the higher MR; a
# point above and right of another beats it on both.

# %%
for sequence, group in runtime.groupby("sequence", sort=False):
    figure = runtime_vs_mr.fps_vs_max_recall(group, caption=captions[sequence])
    plots.save(figure, figures / f"fps_vs_max_recall_{sequence}.png")
    plt.show()
