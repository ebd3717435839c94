"""Write the analysis notebooks (the paper's tables and figures) from the cells below.

Thin like the stage notebooks: a ``parameters`` cell, then calls into
``gvbench_nb.evaluation.analysis`` and ``gvbench_nb.reporting.analysis_plots``. They read only written
results; with their defaults they first run what is missing on the sample
(``analysis.ensure_results``), so they work on a fresh clone. Rewrite them with:
    python notebooks/build_analysis_notebooks.py
"""

from __future__ import annotations



from build_notebooks import write_notebooks  # same folder: run this file as a script


PARAMETERS = """\
output_dirs = ["../outputs/sample"]  # sequence output folders holding results.csv
params_files = ["../params/sample.yaml"]  # run these first where results are missing ([]: run nothing)
ensure_methods = ["sift-nn"]  # the methods ensure_results runs when their pairs.csv is missing
output_dir = "../outputs/sample/analysis"  # figures (PNG) and tables are written here"""

SETUP = """\
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
      f"{', '.join(results['sequence'].unique())}")"""

NOTEBOOKS: dict[str, list[tuple[str, str]]] = {
    "analysis_results_table.ipynb": [
        ("md", "# Results across sequences\nAP and max recall at 100% precision (MR) of every method, profile "
               "and sequence, in %: one row a (method, profile). **Bold**: the best of its column. Published "
               "values (grey italics) stand only beside ours of the same protocol: *paper* (the GV-Bench "
               "paper's table) in the rows of the paper profile, *GV-Bench repository* (its README's table) "
               "in those of the repository profile. Then MR across sequences (the paper's Fig. 1)."),
        ("params", PARAMETERS + """
paper_table = None  # a paper_table.csv of your own; None: the one shipped in gvbench_nb/reference_values"""),
        ("code", SETUP),
        ("code", """\
paper = analysis.load_paper_table(paper_table)
repository = analysis.load_repository_table()
print(f"paper's table: {len(paper)} rows" if len(paper) else "paper's table not found: no paper values")
joined = analysis.join_paper_table(results, paper, repository)
wide = analysis.results_table(joined)
joined.to_csv(figures / "results_with_paper.csv", index=False)
analysis.style_results_table(wide)"""),
        ("md", "For context, the published tables (GV-Bench official sequences; values as published) for the "
               "methods we ran: the paper's (hloc chain) and the GV-Bench repository's (its current code). "
               "Each is comparable with ours only under its own profile, on the same sequence and pairs, "
               "and not with the other."),
        ("code", """\
for table, source in ((paper, analysis.PAPER_LABEL), (repository, analysis.REPOSITORY_LABEL)):
    if len(table) and table["method"].isin(results["method"]).any():
        display(Markdown(f"**{source}**"))
        display(analysis.style_results_table(analysis.paper_reference_table(table, results["method"].unique(),
                                                                            source=source)))
    else:
        print(f"no {source} values for these methods")"""),
        ("code", """\
runtime = analysis.runtime_table(results)
runtime[["sequence", "profile", "method", "device", "seconds_per_pair", "fps"]]"""),
        ("code", """\
figure = analysis_plots.max_recall_radar(
    joined, title="max recall at 100% precision (ours: solid, paper profile / dash-dot, repository profile; "
                  "published: dashed, paper / dotted, GV-Bench repository)")
plots.save(figure, figures / "max_recall_radar.png"); plt.show()"""),
    ],
    "analysis_runtime_vs_mr.ipynb": [
        ("md", "# Runtime vs max recall\nSeconds per pair split by stage (extraction amortised over the pairs "
               "that share an image, matching, RANSAC verification) and FPS = 1 / seconds per pair against MR "
               "(the paper's Fig. 7). The device, profile and image size come from each run's `run.json`."),
        ("params", PARAMETERS + """
cache_dir = None  # feature cache (for image sizes); None: <output_dir>/../cache"""),
        ("code", SETUP),
        ("code", """\
runtime = analysis.runtime_table(results)
runtime"""),
        ("code", """\
for sequence, group in runtime.groupby("sequence", sort=False):
    folder = results.loc[results["sequence"] == sequence, "output_dir"].iloc[0]
    caption = f"{sequence}: " + analysis.run_description(folder, list(group["method"]), cache_dir)
    print(caption)
    figure = analysis_plots.seconds_per_pair_stacked(group, caption=caption)
    plots.save(figure, figures / f"seconds_per_pair_{sequence}.png"); plt.show()
    figure = analysis_plots.fps_vs_max_recall(group, caption=caption)
    plots.save(figure, figures / f"fps_vs_max_recall_{sequence}.png"); plt.show()"""),
    ],
    "analysis_inlier_histograms.ipynb": [
        ("md", "# Inlier distributions of true and false pairs\nInliers divided by each method's largest count "
               "(as the paper's Figs. 6, 8, 9). The dashed line is the top false pair's score: only true pairs "
               "right of it count towards MR; true pairs with zero inliers are out of reach at any threshold."),
        ("params", PARAMETERS),
        ("code", SETUP),
        ("code", """\
for folder in output_dirs:
    tables = analysis.load_pairs_tables(folder)
    sequence = results.loc[results["output_dir"] == str(Path(folder)), "sequence"].iloc[0]
    display(Markdown(f"## {sequence}"))
    display(analysis.inlier_overlap_table(tables))
    figure = analysis_plots.normalised_inlier_histograms(tables, title=f"{sequence}: normalised inliers, true vs false")
    plots.save(figure, figures / f"normalised_inliers_{sequence}.png"); plt.show()"""),
    ],
    "analysis_failures.ipynb": [
        ("md", "# Failures: top false positives and false negatives\nFalse positives: the highest-scoring false "
               "pairs; false negatives: the lowest-scoring true pairs, drawn with inlier matches green and "
               "outliers red (from the match store and the feature cache). Offsets are the ground-truth "
               "distance of a pair: frames |i - j|, and metres/degrees where the sequence has `poses.csv`. "
               "False positives just outside the ground-truth threshold are the label ambiguity the paper "
               "discusses."),
        ("params", PARAMETERS + """
k = 3  # pairs drawn a method and kind
near_low = 3  # false positives this many frames from the query or more ...
near_high = 5  # ... up to this many are 'just outside' the ground-truth threshold
near_top_k = 20  # how many top false positives are checked for near misses
cache_dir = None  # feature cache; None: <output_dir>/../cache"""),
        ("code", SETUP),
        ("code", """\
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
near_misses"""),
    ],
    "analysis_uncertainty.ipynb": [
        ("md", "# How sure are the rankings? A query bootstrap\nQueries are resampled with replacement (a pair "
               "goes with its query), the same resamples for every method, and AP and MR recomputed: 95% "
               "percentile intervals, and for every two methods the share of resamples where one beats the other. "
               "'>' marks a row method better than the column's in more than 97.5% of resamples."),
        ("params", PARAMETERS + """
n_resamples = 1000
seed = 0"""),
        ("code", SETUP),
        ("code", """\
all_intervals = []
for folder in output_dirs:
    tables = analysis.load_pairs_tables(folder)
    result = analysis.bootstrap(tables, n_resamples, seed)
    sequence = results.loc[results["output_dir"] == str(Path(folder)), "sequence"].iloc[0]
    intervals = result.intervals().assign(sequence=sequence)
    all_intervals.append(intervals)
    display(Markdown(f"## {sequence}: {result.n_queries} queries, {result.n_pairs} pairs, {n_resamples} resamples"))
    display(intervals)
    figure = analysis_plots.bootstrap_intervals(intervals, title=f"{sequence}: 95% bootstrap intervals")
    plots.save(figure, figures / f"bootstrap_intervals_{sequence}.png"); plt.show()
    for metric in ("max_recall", "ap"):
        if len(result.methods) > 1:
            display(Markdown(f"**{metric}**: row vs column ('>' significantly better, '<' worse, '~' not significant)"),
                    result.ranking_matrix(metric), result.pairwise(metric))
        else:
            print("one method: no ranking to test")
pd.concat(all_intervals).to_csv(figures / "bootstrap_intervals.csv", index=False)"""),
    ],
}


if __name__ == "__main__":
    write_notebooks(NOTEBOOKS)
