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
# # Explore one pair across methods
# Pick a sequence (its params file), a pair (by index, or a method's top false positive or
# false negative) and the methods to compare; see each method's matches and RANSAC inliers on
# that pair, its score (`num_inliers`, and the distinct keypoints among the inliers) and the rank of that score among the method's scores.
# Everything is read from what the runs wrote: each method's `pairs.csv` in the run the folder shows, the match
# stores and the feature cache; nothing is matched again (unless `compute_missing` runs a
# method that has no results yet). In JupyterLab, controls at the end re-draw every view for
# another pick, pair or methods; in a batch run (papermill, nbmake) set the parameters below.
# `python -m gvbench_nb explore OUTPUT_DIR` opens a working copy of this notebook pointed at a
# run's folder (`OUTPUT_DIR/explore/explore_pairs.ipynb`): edit and save that copy, not this file.

# %%
from pathlib import Path

from IPython.display import display

from gvbench_nb import notebook
from gvbench_nb.evaluation import run_tables
from gvbench_nb.studies import explore_pairs as explore

# %% tags=["parameters"]
params_file = "../params/sample.yaml"  # the sequence: a params YAML whose output_dir holds the runs
methods = None  # methods to compare, e.g. ["sift-nn", "orb-nn"]; None: every method the run holds
pick = "false_positive"  # 'index' (pair_index below), 'false_positive' or 'false_negative' (of pick_method)
pair_index = 0  # the pair shown when pick is 'index' (row of pairs.csv)
pick_method = None  # whose false positives / negatives are ranked (None: the first of methods)
pick_rank = 1  # 1: the top one, 2: the next, ...
# True: run the methods whose pairs.csv is missing; False: an error naming the command that makes them
compute_missing = False
output_dir = None  # the runs' folder; default: the params file's output_dir
cache_dir = None  # feature and match cache; None: the one the run recorded (run.json)
figures_dir = None  # where the table and figures are written; default: <output_dir>/explore
controls = "auto"  # 'auto' (widgets in a live kernel with ipywidgets), 'widgets' or 'none'

# %%
methods = list(methods or explore.default_methods(params_file, output_dir))
out = notebook.require_results(
    params_file, methods, compute_missing=compute_missing, evaluate=False, output_dir=output_dir
)
figures = Path(figures_dir) if figures_dir else out / "explore"
tables = run_tables.load_pairs_tables(out, methods)
run = run_tables.load_run(out, next(iter(tables)))
print(f"{run['sequence']}: {len(next(iter(tables.values())))} pairs; methods {', '.join(tables)} ({out})")


def draw(index: int, shown: list[str]) -> dict:
    """Every view of pair ``index`` for the methods ``shown``: table, matches, score histograms."""
    return explore.pair_views(out, {m: tables[m] for m in shown}, index, figures, cache_dir)


chosen = explore.choose_pair(tables, pick, pair_index, pick_method, pick_rank)
views = draw(chosen, list(tables))

# %% [markdown]
# ## The pair and its score in every method
# `rank` is the pair's place among the method's `n_pairs` scores (1: the highest; tied pairs
# share the best rank of their tie). A true pair (`label` 1) counts toward max recall at 100 %
# precision only when it scores above every false pair (`above_all_false`); a false pair that
# ranks near the top is what caps that recall. The table is written to
# `<figures>/explore_pair.csv`.

# %%
display(explore.shown_table(views["table"]))

# %% [markdown]
# ## Matches and inliers, one row a method
# Green lines are the matches RANSAC kept (inliers; their count is the score), red the ones it
# rejected (at most 300 drawn). On a true pair, look for green lines that join the same scene
# points; on a false pair, green lines are the false evidence: repeated texture, sky, road
# markings or a similar facade. Compare how many lines each method draws against its rank:
# the same count can rank high for one method and low for another.

# %%
display(views["matches"])

# %% [markdown]
# ## Where the score sits among the method's scores
# Each method's scores of true pairs (green) and false pairs (red); the black line is this
# pair's score. A false pair far right of the red mass is an outlier worth a look; a true pair
# left of the highest red score is lost at 100 % precision whatever the threshold.

# %%
display(views["scores"])

# %% [markdown]
# ## Controls
# In a live kernel with ipywidgets, the controls below re-draw all three views (table, matches,
# score histograms) for another pick, pair, ranking method or set of methods; the `pair_index`
# box shows the pair each pick chose. In a batch run (papermill, nbmake) this cell only says so.

# %%
if explore.use_widgets(controls):
    explorer = explore.ExploreControls(tables, draw, pick, chosen, pick_method, pick_rank)
    display(explorer.widget())
    explorer.redraw()
else:
    print(
        f"controls: none (controls={controls!r}; widgets need a live kernel and ipywidgets): "
        "set the parameters cell and run again"
    )
