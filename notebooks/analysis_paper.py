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
# # The paper's tables and figures
# Table II (the sequences), Table III (AP and MR with their average, 1st / 2nd / 3rd of
# each column marked), Fig. 1 (the radar of the published max recall, as published) and
# Fig. 8's grouping (each method across sequences), from the runs given and the official
# lists found in the data folder.

# %%
from typing import Optional

import matplotlib.pyplot as plt
from IPython.display import Markdown, display

from gvbench_nb import notebook
from gvbench_nb.evaluation import plots, run_tables
from gvbench_nb.studies import paper

# %% tags=["parameters"]
output_dirs: list = ["../outputs/sample"]  # sequence output folders holding results.csv
# params files whose output folders must hold ensure_methods' results ([]: no check)
params_files: list = ["../params/sample.yaml"]
ensure_methods: list = ["sift-nn"]
# True: run ensure_methods where their pairs.csv is missing; False: an error naming
# the command that makes them
compute_missing: bool = False
output_dir: str = "../outputs/sample/analysis"  # figures (PNG) and tables are written here
# the folder of the official GV-Bench lists (<name>.txt); None: gvbench_gt in the data folder
lists_dir: Optional[str] = None

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
# **Table II**, the sequences: each run's pairs and each official list, counted, beside
# what the paper's text states. They differ: the Nordland list holds 1,407 queries and
# 28,124 pairs where the text says 1,415 and 28,300; the UAcampus list 640 queries with
# 15 candidates each (9,600 pairs) where the text says 647 with their top 10. Condition
# as the paper's sources name it; '-': not stated. Also written to `table_ii.csv`.

# %%
summary = paper.sequence_summary(output_dirs, lists_dir)
summary.to_csv(figures / "table_ii.csv", index=False)
display(paper.summary_text(summary).style.hide(axis="index"))

# %% [markdown]
# **Table III**, ours: AP and MR (%) of every (method, profile) on each recorded
# sequence, and with two or more their average (blank for a row missing one). In each
# column the 1st is bold, the 2nd underlined, the 3rd italic. Routes the package rendered
# (synthetic) get a table of their own, never averaged. Also written to `table_iii.csv`
# (and `table_iii_synthetic.csv`).

# %%
real, synthetic = paper.real_and_synthetic(results)
for rows, name, what in ((real, "table_iii", "recorded"), (synthetic, "table_iii_synthetic", "synthetic")):
    if rows.empty:
        print(f"no {what} sequence among the runs")
        continue
    table = paper.table_iii(rows, average=rows is real)
    table.to_csv(figures / f"{name}.csv")
    display(Markdown(f"**{what.capitalize()} sequences**"), paper.style_table_iii(table))

# %% [markdown]
# **Fig. 1**, the published max recall alone: the paper's table (the hloc chain), and
# the GV-Bench repository's (its current code), every method each reports, values as
# published. Nothing of ours is drawn here.

# %%
for source, name in ((run_tables.PAPER_LABEL, "paper"), (run_tables.REPOSITORY_LABEL, "repository")):
    figure = paper.published_radar(source)
    plots.save(figure, figures / f"published_max_recall_radar_{name}.png")
    plt.show()

# %% [markdown]
# **Fig. 8's grouping**: each method's MR and AP on every sequence side by side (ours).
# A method whose bars fall on one sequence is hurt by that sequence's condition.

# %%
figure = paper.method_across_sequences(results)
plots.save(figure, figures / "method_across_sequences.png")
plt.show()
