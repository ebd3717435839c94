"""Write the stage notebooks from the cell sources below (run after editing them).

The notebooks stay thin: a ``parameters`` cell papermill overrides, then calls into
``gvbench_nb``. Running this file rewrites them without outputs:
    python notebooks/build_notebooks.py
"""

from __future__ import annotations

from pathlib import Path

import nbformat
from nbformat.v4 import new_code_cell, new_markdown_cell, new_notebook

HERE = Path(__file__).resolve().parent

SETUP = """\
from pathlib import Path
import matplotlib.pyplot as plt
import pandas as pd
from IPython.display import display
from gvbench_nb import config, pipeline, plots, sequences"""

NOTEBOOKS: dict[str, list[tuple[str, str]]] = {
    "00_build_sequence.ipynb": [
        ("md", "# 00 - Build a sequence the GV-Bench way\nTop-N retrieval by a global descriptor, labels by a ground-truth rule: "
               "writes the pair file and its card (`<stem>.card.json`, `.card.md`, `.candidates.csv`)."),
        ("params", """\
params_file = "../params/sample_retrieval.yaml"  # a params YAML with pairs_builder: retrieval
descriptor = None  # 'vlad', 'bow' or 'netvlad'; default: the params'
top_n = None  # candidates a query; default: the params'
compare_descriptors = ["vlad", "bow"]  # recall@k figure, each with the params' descriptor_options (netvlad: weights, slow on CPU)
strip_count = 4  # queries shown with their top candidates
output_dir = None  # figures go here; default: the params file's output_dir"""),
        ("code", """\
from pathlib import Path
import matplotlib.pyplot as plt
import pandas as pd
from IPython.display import Markdown, display
from gvbench_nb import build, plots"""),
        ("code", """\
params = config.load_build_params(params_file, descriptor=descriptor, top_n=top_n, output_dir=output_dir)
figures = Path(params["output_dir"])
card = build.build_sequence(params)
build.check_card(card["files"]["pairs"])  # the card's counts are the pair file's
display(Markdown(build.card_markdown(card)))"""),
        ("code", """\
curves = build.recall_curves(params, compare_descriptors)
display(curves.pivot(index="k", columns="descriptor", values="recall").round(3).T)
figure = build.plot_recall_curves(curves, title=f"{card['sequence']}: retrieval recall@k ({curves.queries_evaluated.iloc[0]} queries)")
plots.save(figure, figures / "build_recall_at_k.png"); plt.show()"""),
        ("code", """\
candidates = pd.read_csv(card["files"]["candidates"])
shown = build.strip_queries(candidates, strip_count)
figure = build.candidate_strips(params["image_root"], candidates, shown, k=min(5, card["top_n"]),
                                title=f"{card['sequence']}: top candidates by {card['descriptor']} (green true, red false)")
plots.save(figure, figures / "build_candidates.png"); plt.show()"""),
    ],
    "01_sequence.ipynb": [
        ("md", "# 01 - What a sequence holds\nCounts, positives a query and example pairs of one sequence."),
        ("params", """\
params_file = "../params/sample.yaml"  # a params YAML (paths inside are relative to it); a run passes its params.resolved.yaml
limit = None  # first N pairs only
output_dir = None  # default: the params file's output_dir"""),
        ("code", SETUP),
        ("code", """\
params = config.load_params(params_file, limit=limit, output_dir=output_dir)
sequence = config.prepare_sequence(params)
figures = Path(params["output_dir"])
summary = sequences.summarize(sequence)
pd.Series(summary, name=sequence.name).to_frame()"""),
        ("code", """\
pairs = sequence.to_frame()
sequence.check_images()  # names the first missing image and its pair
figure = plots.positives_per_query(pairs, title=f"{sequence.name}: true references a query")
plots.save(figure, figures / "sequence_positives_per_query.png"); plt.show()"""),
        ("code", """\
examples = pd.concat([pairs[pairs.label == 1].head(2), pairs[pairs.label == 0].tail(2)])
figure = plots.example_pairs(sequence.image_root, examples, title=f"{sequence.name}: example pairs (query | reference)")
plots.save(figure, figures / "sequence_examples.png"); plt.show()"""),
    ],
    "02_verify.ipynb": [
        ("md", "# 02 - Verify: one method on one sequence\nExtract (cached), match, fit F with RANSAC; writes `<output_dir>/<method>/pairs.csv`."),
        ("params", """\
params_file = "../params/sample.yaml"
method = "sift-nn"  # a name from `python -m gvbench_nb methods`
profile = None  # 'paper' or 'repository'; default: the params file's
limit = None
output_dir = None"""),
        ("code", SETUP),
        ("code", """\
params = config.load_params(params_file, limit=limit, output_dir=output_dir, profile=profile)
sequence = config.prepare_sequence(params)
table = pipeline.run_method(sequence, method, params["profile"], Path(params["output_dir"]), Path(params["cache_dir"]),
                            device=params["device"], seed=params["seed"])
print(f"{method} ({params['profile']}) on {sequence.name}: {len(table)} pairs -> {pipeline.method_dir(params['output_dir'], method) / 'pairs.csv'}")
table.head()"""),
        ("code", """\
table.groupby("label")[["num_matches", "num_inliers"]].describe().T"""),
        ("code", """\
figure = plots.inlier_histogram(table, title=f"{method} on {sequence.name}")
plots.save(figure, Path(params["output_dir"]) / f"inliers_{method}.png"); plt.show()"""),
    ],
    "03_evaluate.ipynb": [
        ("md", "# 03 - Evaluate: AP, MR and PR curves of every method with results\nReads only the runs' `pairs.csv`; writes `results.csv` and `pr_curves.png`."),
        ("params", """\
params_file = "../params/sample.yaml"
methods = None  # default: every method with results in output_dir
output_dir = None"""),
        ("code", SETUP),
        ("code", """\
params = config.load_params(params_file, output_dir=output_dir)
out = Path(params["output_dir"])
results = pipeline.evaluate(out, methods)
print(f"results table: {out / 'results.csv'}")
results"""),
        ("code", """\
tables = {m: pipeline.load_pairs_table(out, m) for m in results["method"]}
figure = plots.pr_curves(tables, title=f"{params['sequence']}: precision-recall (dot: MR)")
plots.save(figure, out / "pr_curves.png"); plt.show()"""),
    ],
}


def build(name: str, cells: list[tuple[str, str]]) -> nbformat.NotebookNode:
    notebook = new_notebook()
    notebook.metadata["kernelspec"] = {"name": "python3", "display_name": "Python 3", "language": "python"}
    notebook.metadata["language_info"] = {"name": "python"}
    for kind, source in cells:
        if kind == "md":
            notebook.cells.append(new_markdown_cell(source))
        else:
            cell = new_code_cell(source)
            if kind == "params":
                cell.metadata["tags"] = ["parameters"]
            notebook.cells.append(cell)
    for index, cell in enumerate(notebook.cells):
        cell["id"] = f"{Path(name).stem.replace('_', '-')}-{index}"  # stable ids: clean diffs
    return notebook


def write_notebooks(notebooks: dict[str, list[tuple[str, str]]]) -> None:
    """Write each notebook beside this file (the other builders call this too)."""
    for name, cells in notebooks.items():
        nbformat.write(build(name, cells), HERE / name)
        print("wrote", HERE / name)


if __name__ == "__main__":
    write_notebooks(NOTEBOOKS)
