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
# that pair, its score (`num_inliers`) and the rank of that score among the method's scores.
# Everything is read from what the runs wrote: `<output_dir>/<method>/pairs.csv`, the match
# stores and the feature cache; nothing is matched again (unless `compute_missing` runs a
# method that has no results yet). With a live kernel and ipywidgets installed, controls at
# the end re-draw everything for another pair; otherwise (papermill, nbmake) set the
# parameters below.

# %%
from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np
from IPython.display import display

from gvbench_nb import notebook
from gvbench_nb.data.images import read_image
from gvbench_nb.evaluation import analysis, explore
from gvbench_nb.reporting import plots

# %% tags=["parameters"]
params_file = "../params/sample.yaml"  # the sequence: a params YAML whose output_dir holds the runs
methods = ["sift-nn"]  # methods to compare, each with its run, e.g. ["sift-nn", "orb-nn", "xfeat-nn"]
pick = "false_positive"  # 'index' (pair_index below), 'false_positive' or 'false_negative' (of pick_method)
pair_index = 0  # the pair shown when pick is 'index' (row of pairs.csv)
pick_method = None  # whose false positives / negatives are ranked (None: the first of methods)
pick_rank = 1  # 1: the top one, 2: the next, ...
# True: run the methods whose pairs.csv is missing; False: an error naming the command that makes them
compute_missing = False
output_dir = None  # the runs' folder; default: the params file's output_dir
cache_dir = None  # feature cache; default: <output_dir>/../cache
figures_dir = None  # where the table and figures are written; default: <output_dir>/explore
controls = "auto"  # 'auto' (widgets in a live kernel with ipywidgets), 'widgets' or 'none'

# %%
out = notebook.require_results(
    params_file, methods, compute_missing=compute_missing, evaluate=False, output_dir=output_dir
)
figures = Path(figures_dir) if figures_dir else out / "explore"
figures.mkdir(parents=True, exist_ok=True)
tables = explore.load_tables(out, methods)
run = analysis.load_run(out, next(iter(tables)))
image_root = Path(run["image_root"])
print(f"{run['sequence']}: {len(next(iter(tables.values())))} pairs; methods {', '.join(tables)} ({out})")

# %% [markdown]
# ## The pair and its score in every method
# `rank` is the pair's place among the method's `n_pairs` scores (1: the highest; tied pairs
# share the best rank of their tie). A true pair (`label` 1) counts toward max recall at 100 %
# precision only when it scores above every false pair (`above_all_false`); a false pair that
# ranks near the top is what caps that recall. The table is written to
# `<figures>/explore_pair.csv`.


# %%
def show_table(index: int):
    view = explore.pair_across_methods(tables, index)
    view.to_csv(figures / "explore_pair.csv", index=False)
    display(view)
    return view


chosen = explore.choose_pair(tables, pick, pair_index, pick_method, pick_rank)
view = show_table(chosen)

# %% [markdown]
# ## Matches and inliers, one row a method
# Green lines are the matches RANSAC kept (inliers; their count is the score), red the ones it
# rejected (at most 300 drawn). On a true pair, look for green lines that join the same scene
# points; on a false pair, green lines are the false evidence: repeated texture, sky, road
# markings or a similar facade. Compare how many lines each method draws against its rank:
# the same count can rank high for one method and low for another.


# %%
def show_matches(view):
    figure, axes = plt.subplots(len(view), 1, figsize=(10, 3.4 * len(view)), squeeze=False)
    first = view.iloc[0]
    image0, image1 = read_image(image_root / first["query"]), read_image(image_root / first["reference"])
    for axis, row in zip(axes[:, 0], view.itertuples()):
        lines = analysis.match_lines(out, row.method, row.query, row.reference, cache_dir)
        plots.draw_matches(image0, image1, lines["points0"], lines["points1"], lines["inlier_mask"], axis=axis)
        axis.set_title(
            f"{row.method}: score {row.score} ({row.num_inliers} inliers of {row.num_matches} matches), "
            f"rank {row.rank} of {row.n_pairs}",
            fontsize=9,
        )
    kind = "true" if first["label"] == 1 else "false"
    figure.suptitle(f"{run['sequence']} pair {first['pair_index']} ({kind}): {first['query']} | {first['reference']}")
    figure.tight_layout()
    plots.save(figure, figures / f"explore_pair_{first['pair_index']}.png")
    plt.show()


show_matches(view)

# %% [markdown]
# ## Where the score sits among the method's scores
# Each method's scores of true pairs (green) and false pairs (red); the black line is this
# pair's score. A false pair far right of the red mass is an outlier worth a look; a true pair
# left of the highest red score is lost at 100 % precision whatever the threshold.


# %%
def show_scores(view):
    figure, axes = plt.subplots(1, len(view), figsize=(4 * len(view), 3), squeeze=False)
    for axis, row in zip(axes[0], view.itertuples()):
        table = tables[row.method]
        bins = np.histogram_bin_edges(table["score"], bins=min(40, max(5, table["score"].nunique())))
        for label, colour, name in ((1, "tab:green", "true"), (0, "tab:red", "false")):
            axis.hist(
                table.loc[table["label"] == label, "score"],
                bins=bins,
                histtype="step",
                color=colour,
                label=f"{name} pairs",
            )
        axis.axvline(row.score, color="black", linewidth=1.5, label=f"this pair (rank {row.rank})")
        axis.set(xlabel="score (RANSAC inliers)", ylabel="pairs", title=row.method)
        axis.legend(fontsize=7)
    figure.tight_layout()
    plots.save(figure, figures / f"explore_scores_{view.iloc[0]['pair_index']}.png")
    plt.show()


show_scores(view)

# %% [markdown]
# ## Controls
# In a live kernel with ipywidgets installed, the controls below re-draw the three views above
# for another pair or other methods. In a batch run (papermill, nbmake) this cell only says so.

# %%
if explore.use_widgets(controls):
    import ipywidgets as widgets

    pick_box = widgets.Dropdown(options=list(explore.PICKS), value=pick, description="pick")
    index_box = widgets.BoundedIntText(
        value=chosen, min=0, max=len(next(iter(tables.values()))) - 1, description="pair_index"
    )
    rank_box = widgets.BoundedIntText(value=pick_rank, min=1, max=1000, description="pick_rank")
    method_box = widgets.Dropdown(
        options=list(tables), value=pick_method or next(iter(tables)), description="pick_method"
    )
    shown_box = widgets.SelectMultiple(options=list(tables), value=tuple(tables), description="methods")
    area = widgets.Output()

    def redraw(_change=None):
        global tables
        with area:
            area.clear_output(wait=True)
            tables = explore.load_tables(out, list(shown_box.value) or None)
            try:
                index = explore.choose_pair(
                    tables,
                    pick_box.value,
                    index_box.value,
                    method_box.value if method_box.value in tables else None,
                    rank_box.value,
                )
            except ValueError as error:
                print(error)
                return
            shown = show_table(index)
            show_matches(shown)
            show_scores(shown)

    for box in (pick_box, index_box, rank_box, method_box, shown_box):
        box.observe(redraw, names="value")
    display(widgets.VBox([widgets.HBox([pick_box, index_box, rank_box]), widgets.HBox([method_box, shown_box]), area]))
    redraw()
else:
    print(
        f"controls: none (controls={controls!r}; widgets need a live kernel and ipywidgets): "
        "set the parameters cell and run again"
    )
