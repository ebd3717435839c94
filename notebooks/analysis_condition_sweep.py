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
# # Controlled condition study: when does verification break?
# The synthetic route (`gvbench_nb/data/synthetic/`) is rendered twice: a clear reference
# drive and an offset query drive. The query drive is re-rendered with **one** condition
# (illumination, season or weather) at each strength; poses, pairs and labels stay the
# same, so every change in AP and MR is the condition's doing. The reference drive is
# extracted once and shared by every cell.
#
# * **MR**: recall at precision 1 (the paper's metric); **breaking strength**: the
#   lowest strength at which MR falls below half its clear (strength 0) value, linearly
#   interpolated between grid strengths.
# * **aliasing share**: among the hardest tenth of the false pairs (highest scores), the
#   fraction that are look-alikes - false pairs whose reference views the repeated
#   façade block from the pose the query views the original from. 1 = every one of the
#   hardest negatives is a look-alike; the dotted line is chance (the look-alikes' share
#   of all false pairs).

# %%
from typing import Optional, Union

import matplotlib.pyplot as plt
from IPython.display import display

from gvbench_nb import notebook
from gvbench_nb.evaluation import plots
from gvbench_nb.runner import config
from gvbench_nb.studies import condition_sweep

# %% tags=["parameters"]
methods: list = ["sift-nn"]  # names from `python -m gvbench_nb methods`
profile: Union[str, dict] = "paper"  # 'paper' or 'repository' for all, or a mapping method -> profile
conditions: list = ["illumination", "season", "weather"]
strengths: list = [0.0, 0.5, 1.0]  # 0 (clear) is always included
# route length; from ~20 frames the repeated façade block (look-alike pairs) is in it
n_frames: int = 20
image_size: list = [320, 240]  # (width, height) of the renders
seed: int = 0
# torch/OpenCV threads (None: every core); one is fastest on a small busy machine
threads: Optional[int] = 1
output_dir: str = "../outputs/condition_sweep_nbmake"

# %% [markdown]
# Run every (condition, strength, method) cell not yet in `sweep.csv`, then show the
# table: one row a cell with its AP, MR, aliasing share and its chance level, and the
# pair counts (the same in every cell).

# %%
notebook.check_parameters(globals())  # papermill's -p passes text: a list is given with -y
out = config.outputs_path(output_dir)  # output_dir, or where $GVBENCH_OUTPUTS moves it
sweep = condition_sweep.run_sweep(
    out,
    methods,
    conditions=conditions,
    strengths=strengths,
    seed=seed,
    n_frames=n_frames,
    profile=profile,
    image_size=image_size,
    threads=threads,
)
print(f"{len(sweep)} cells -> {out / 'sweep.csv'}")
display(notebook.table(sweep))

# %% [markdown]
# ## AP, MR and aliasing share against strength, one figure a condition
# One line a method. Falling AP and MR show the condition hurting verification; an
# aliasing share rising above its dotted chance line shows look-alikes taking over the
# hardest false pairs.

# %%
for condition in conditions:
    figure = condition_sweep.plot_condition(sweep, condition)
    plots.save(figure, out / f"sweep_{condition}.png")
    plt.show()

# %% [markdown]
# ## Breaking strengths (MR below half its clear value)
# One row a method, one column a condition: the strength at which its MR drops below
# half its clear value, or why there is none (e.g. not reached within the grid). Also
# written to `breaking_strength.csv`.

# %%
breaking = condition_sweep.breaking_strength(sweep)
breaking.to_csv(out / "breaking_strength.csv", index=False)
display(notebook.table(condition_sweep.breaking_strength_table(sweep)))

# %% [markdown]
# MR against strength, one panel a condition; the dashed mark on each line is its
# breaking strength. The condition whose marks sit furthest left breaks verification
# first.

# %%
figure = condition_sweep.plot_overview(sweep)
plots.save(figure, out / "sweep_max_recall.png")
plt.show()

# %% [markdown]
# ## What the query drive looks like across strengths (the reference drive stays clear)
# One query frame under each condition (rows) at each strength (columns), as rendered.

# %%
figure = condition_sweep.plot_examples(out, conditions, strengths)
plots.save(figure, out / "sweep_examples.png")
plt.show()
