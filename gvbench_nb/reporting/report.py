"""``python -m gvbench_nb report``: the analysis notebooks over every finished sequence, executed by
papermill and converted by nbconvert, behind one summary page (index.html)."""

from __future__ import annotations

import argparse
import datetime as _dt
import logging
import os
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from gvbench_nb.io_utils import add_described_command, atomic_write_text
from gvbench_nb.reporting.execute import NotebookFailedError, execute_notebook
from gvbench_nb.runner import config

log = logging.getLogger(__name__)

if TYPE_CHECKING:
    import pandas as pd
    from nbconvert import HTMLExporter

# `analysis` (torch, OpenCV) is imported inside the functions: `--help` stays instant.

PER_SEQUENCE_NOTEBOOKS = (
    "analysis_runtime_vs_mr.ipynb",
    "analysis_inlier_histograms.ipynb",
    "analysis_failures.ipynb",
    "analysis_uncertainty.ipynb",
)
ACROSS_SEQUENCES_NOTEBOOK = "analysis_results_table.ipynb"
# Figures shown on the summary page, per sequence ({sequence} filled in).
KEY_FIGURES = (
    "fps_vs_max_recall_{sequence}.png",
    "seconds_per_pair_{sequence}.png",
    "normalised_inliers_{sequence}.png",
    "bootstrap_intervals_{sequence}.png",
)

HELP = "run the analysis notebooks over finished sequences and write an HTML report"
DESCRIPTION = """\
Reads the output folders named (each showing finished runs; without any, every such folder
under --outputs-root, or the ones named by --sequences) from their runs, executes the analysis
notebooks on them with papermill (runtime vs MR, inlier histograms, failures, bootstrap
uncertainty; the results table once across all sequences), converts them to HTML and writes
<output-dir>/index.html: the combined results table (ours beside the paper's published values,
labelled 'paper'), the methods a folder leaves out and the collapsed-inlier warnings `results`
gives, the key figures and links to every notebook. Reads only written results: nothing is
re-extracted or re-matched.
"""
EPILOG = """\
examples:
  python -m gvbench_nb report
  python -m gvbench_nb report outputs/sample outputs/gardens_point
  python -m gvbench_nb report --sequences sample,gardens_point --output-dir outputs/report
"""


@dataclass
class ExecutedNotebook:
    sequence: str  # '' for the across-sequences notebook
    notebook: Path
    html: Path | None
    error: str | None = None


def execute_and_convert(
    source: str, target: Path, parameters: dict, sequence: str = "", index: Path | None = None
) -> ExecutedNotebook:
    """Execute one analysis notebook and write its HTML beside it; a failing one is still converted and
    its error returned, not raised, so one sequence cannot sink the report."""
    error = None
    try:
        execute_notebook(source, target, parameters)
    except NotebookFailedError as failure:
        error = f"{failure.ename}: {failure.evalue}"
    html_path = None
    if target.is_file():
        back = {"index_href": Path(os.path.relpath(index, target.parent)).as_posix()} if index else {}
        body, _ = _offline_exporter().from_filename(str(target), resources=back)
        html_path = atomic_write_text(target.with_suffix(".html"), body)
    return ExecutedNotebook(sequence, target, html_path, error)


TEMPLATES = Path(__file__).parent / "templates"


def _offline_exporter() -> HTMLExporter:
    import jinja2
    from nbconvert import HTMLExporter

    # Code cells hidden: the pages show what the notebooks found (a failing cell's traceback stays).
    return HTMLExporter(
        extra_loaders=[jinja2.FileSystemLoader(TEMPLATES)],
        template_file="offline.html.j2",
        exclude_input=True,
        exclude_input_prompt=True,
        exclude_output_prompt=True,
    )


def _relative(path: Path, start: Path) -> str:
    return path.resolve().relative_to(start.resolve()).as_posix()


def summary_page(report_dir: Path, output_dirs: list[Path], executed: list[ExecutedNotebook]) -> str:
    """The index page: the combined results table, what it leaves out or warns of, key figures, links (all relative)."""
    from gvbench_nb.evaluation import collapsed_inliers, plots, run_tables
    from gvbench_nb.runner import scoring
    from gvbench_nb.studies import inlier_histograms, results_table, runtime_vs_mr

    results = run_tables.load_results(output_dirs)  # the runs' own numbers, never a results.csv
    paper, repository = results_table.load_paper_table(), results_table.load_repository_table()
    wide = results_table.results_table(results_table.join_paper_table(results, paper, repository))
    folders = []
    for folder, name in page_folders(output_dirs).items():
        rows = results[results["output_dir"] == str(folder)]
        tables = {m: scoring.load_pairs_table(folder, m) for m in rows["method"]}
        sequence = str(rows["sequence"].iloc[0])
        figures = [report_dir / name / figure.format(sequence=sequence) for figure in KEY_FIGURES]
        intervals = report_dir / name / "bootstrap_intervals.csv"
        folders.append(
            {
                "path": str(folder),
                "sequence": sequence,
                "left_out": scoring.left_out(folder),
                "warnings": collapsed_inliers.collapse_warnings(tables),
                "intervals": _intervals_html(intervals, rows) if intervals.is_file() else "",
                # The figures a run is left out of, and why: imported scores have no seconds, and
                # those imported from a table of scores no inlier counts.
                "absent": runtime_vs_mr.unmeasured_lines(rows) + inlier_histograms.with_inlier_counts(tables)[1],
                "figures": [_relative(f, report_dir) for f in figures if f.is_file()],
            }
        )
    styles = {"-": "solid", "--": "dashed", ":": "dotted"}
    line_styles = ", ".join(
        f"{styles[plots.PROFILE_LINE_STYLES.get(p, ':')]} lines {plots.run_label('', p).strip(' ()')}"
        for p in dict.fromkeys(results["profile"])
    )
    radar = report_dir / "max_recall_radar.png"
    return _render(
        "index.html.j2",
        generated=_dt.datetime.now().isoformat(timespec="seconds"),
        folders=folders,
        table=results_table.style_results_table(wide).to_html(),
        table_note=table_note(wide, paper_found=len(paper) > 0),
        radar=_relative(radar, report_dir) if radar.is_file() else None,
        curves=[_relative(path, report_dir) for path in pr_curve_figures(report_dir, results).values()],
        line_styles=line_styles,
        paper=paper_sections(report_dir, output_dirs, results),
        notebooks=executed,
        relative=lambda path: _relative(path, report_dir),
    )


def table_note(wide: pd.DataFrame, paper_found: bool = True) -> str:
    """The results table's header text: its rows, and only the kinds of columns it has."""
    from gvbench_nb.evaluation import run_tables

    sources, metrics = (set(wide.columns.get_level_values(level)) for level in ("source", "metric"))
    return _render(
        "table_note.html.j2", labels=run_tables, sources=sources, pairs="pairs" in metrics, paper_found=paper_found
    )


def _render(template: str, **context: Any) -> str:
    import jinja2

    loader = jinja2.FileSystemLoader(TEMPLATES)
    return (
        jinja2.Environment(loader=loader, autoescape=True, trim_blocks=True, lstrip_blocks=True)
        .get_template(template)
        .render(**context)
    )


def pr_curve_figures(report_dir: Path, results: pd.DataFrame) -> dict[str, Path]:
    """``<report_dir>/pr_curves_<sequence>.png``: every (method, profile) of ``results`` that ran the sequence."""
    import matplotlib.pyplot as plt

    from gvbench_nb.evaluation import plots
    from gvbench_nb.runner import scoring

    by_sequence: dict[str, dict[tuple[str, str], pd.DataFrame]] = {}
    for row in results.drop_duplicates(["output_dir", "method"]).itertuples():
        tables = by_sequence.setdefault(str(row.sequence), {})
        tables[(str(row.method), str(row.profile))] = scoring.load_pairs_table(Path(row.output_dir), str(row.method))
    written = {}
    for sequence, tables in by_sequence.items():
        figure = plots.pr_curves_by_profile(tables, title=f"{sequence}: precision-recall (dot: MR)")
        written[sequence] = plots.save(figure, report_dir / f"pr_curves_{sequence}.png")
        plt.close(figure)
    return written


def _intervals_html(path: Path, results: pd.DataFrame) -> str:
    import pandas as pd

    from gvbench_nb.evaluation import run_tables

    table = pd.read_csv(path)
    # The intervals are keyed by method; a folder shows one profile a method, which its results name.
    profiles = results.drop_duplicates("method").set_index("method")["profile"]
    table["profile"] = table["method"].map(profiles).fillna("")
    columns = ["method", "profile", "metric", "estimate", "low", "high", "n_valid"]
    shown = run_tables.readable_table(table[columns], ["estimate", "low", "high"], run_tables.run_labels(results))
    return shown.to_html(index=False, float_format=lambda v: f"{v:.1f}")


def _sequence_name(output_dir: Path) -> str:
    """The sequence name the runs recorded (figures are named by it), else the folder name."""
    from gvbench_nb.runner import method_outputs, scoring

    methods = scoring.methods_with_results(output_dir)
    return str(method_outputs.read_run_json(output_dir, methods[0])["sequence"]) if methods else output_dir.name


# Run once across every sequence: the paper's tables and figures, and the deployment questions.
PAPER_NOTEBOOKS = ("analysis_paper.ipynb", "analysis_deployment.ipynb")
PAPER_FIGURES = {
    "Fig. 1: max recall at 100% precision as the paper published it": "published_max_recall_radar_paper.png",
    "The same, as the GV-Bench repository published it (its own code)": "published_max_recall_radar_repository.png",
    "Fig. 8's grouping: each method across sequences (ours)": "method_across_sequences.png",
}


VERIFIER_METHOD = "sift-nn"  # whose cached matches the verifier pages re-score
VERIFIERS_FOLDER = "verifiers"  # the verifier notebooks' output folder in a run folder, as they default


def study_jobs(report_dir: Path, output_dirs: list[Path]) -> list[tuple[str, Path, dict, str]]:
    """The studies' pages where their inputs exist (verifiers.csv, a retrieval build, a sweep.csv beside
    the folders), with the parameters they were run with, so nothing is computed anew."""
    import json

    import yaml

    from gvbench_nb.runner import method_outputs

    jobs: list[tuple[str, Path, dict[str, Any], str]] = []
    for folder in output_dirs:
        target, sequence = report_dir / folder.name, _sequence_name(folder)
        verifiers, verified = folder / VERIFIERS_FOLDER, method_outputs.method_dir(folder, VERIFIER_METHOD)
        if (verifiers / "verifiers.csv").is_file() and (verified / "pairs.csv").is_file():
            # Into the study's own folder: its trained weights and predictions are reused, not redone.
            parameters: dict[str, Any] = {"params_file": None, "results_dir": str(folder), "method": VERIFIER_METHOD}
            for name in ("analysis_verifiers.ipynb", "analysis_doppelgangers.ipynb"):
                jobs.append((name, target / name, {**parameters, "output_dir": str(verifiers)}, sequence))
        params_file = _run_params_file(folder)
        params = yaml.safe_load(params_file.read_text(encoding="utf-8")) if params_file else {}
        if (params or {}).get("pairs_builder") == "retrieval":
            descriptor = (params.get("builder_options") or {}).get("descriptor", "vlad")
            build = {"params_file": str(params_file), "compare_descriptors": [descriptor]}
            build["output_dir"] = str(target / "build")
            jobs.append(("00_build_sequence.ipynb", target / "00_build_sequence.ipynb", build, sequence))
    for sweep in sorted({p.parent.parent for d in output_dirs for p in d.parent.glob("*/images/route.json")}):
        if not (sweep / "sweep.csv").is_file():
            continue
        import pandas as pd

        cells = pd.read_csv(sweep / "sweep.csv")
        route = json.loads((sweep / "images" / "route.json").read_text(encoding="utf-8"))
        sweep_parameters = {
            "methods": list(dict.fromkeys(cells["method"])),
            "profile": dict(zip(cells["method"], cells["profile"])),
            "conditions": list(dict.fromkeys(cells["condition"])),
            "strengths": sorted({float(s) for s in cells["strength"]}),
            "n_frames": route["n_frames"],
            "image_size": route["image_size"],
            "seed": route["seed"],
            "output_dir": str(sweep),
        }
        target = report_dir / f"sweep_{sweep.name}" / "analysis_condition_sweep.ipynb"
        jobs.append(("analysis_condition_sweep.ipynb", target, sweep_parameters, f"sweep {sweep.name}"))
    return jobs


def _run_params_file(folder: Path) -> Path | None:
    """A folder's ``params.resolved.yaml``, else the params file its first method's record names (sharded runs)."""
    from gvbench_nb.runner import method_outputs, runs, scoring

    resolved = runs.resolved_params(folder)
    if resolved is not None:
        return resolved
    for method in scoring.methods_with_results(folder):
        named = (method_outputs.read_run_json(folder, method).get("pairs") or {}).get("params_file")
        return Path(named) if named and Path(named).is_file() else None
    return None


def paper_sections(report_dir: Path, output_dirs: list[Path], results: pd.DataFrame) -> dict[str, Any]:
    """What the index shows of Table II, Table III, Fig. 1, Fig. 8, and the deployment notebook's figure and table."""
    import pandas as pd

    from gvbench_nb.evaluation import run_tables
    from gvbench_nb.studies import deployment, paper

    real, synthetic = paper.real_and_synthetic(results)
    loops = report_dir / "loop_closures.csv"
    loop_table = pd.read_csv(loops) if loops.is_file() else None
    return {
        "counted_by_run": paper.RUN_COUNTED,
        "counted": paper.COUNTED,
        "text": paper.PAPER_TEXT,
        "summary": paper.summary_text(paper.sequence_summary(output_dirs)).to_html(index=False, classes="table-ii"),
        "table_iii": paper.style_table_iii(paper.table_iii(real)).to_html() if len(real) else "",
        "table_iii_synthetic": (
            paper.style_table_iii(paper.table_iii(synthetic, average=False)).to_html() if len(synthetic) else ""
        ),
        "figures": {caption: name for caption, name in PAPER_FIGURES.items() if (report_dir / name).is_file()},
        "transfer": "threshold_transfer.png" if (report_dir / "threshold_transfer.png").is_file() else None,
        "loops": None
        if loop_table is None
        else run_tables.readable_table(loop_table, deployment.LOOP_SHARES, run_tables.run_labels(loop_table)).to_html(
            index=False, float_format=lambda v: f"{v:.1f}", na_rep="-"
        ),
    }


def page_folders(output_dirs: list[Path]) -> dict[Path, str]:
    """Each run folder's sub-folder of the report: its name, with its parent's where two share a name."""
    names = [d.name for d in output_dirs]
    return {d: d.name if names.count(d.name) == 1 else f"{d.parent.name}-{d.name}" for d in output_dirs}


def write_report(report_dir: Path, output_dirs: list[Path]) -> tuple[Path, list[ExecutedNotebook]]:
    """Execute every analysis notebook, convert to HTML, write ``index.html``."""
    from gvbench_nb.io_utils import progress_bar

    report_dir = report_dir.resolve()
    report_dir.mkdir(parents=True, exist_ok=True)
    output_dirs = [d.resolve() for d in output_dirs]
    # params_files=[]: the report runs nothing, it only reads what runs wrote.
    every = {"output_dirs": [str(d) for d in output_dirs], "params_files": [], "output_dir": str(report_dir)}
    jobs = [(ACROSS_SEQUENCES_NOTEBOOK, report_dir / ACROSS_SEQUENCES_NOTEBOOK, every, "")]
    for folder, folder_name in page_folders(output_dirs).items():
        one = {"output_dirs": [str(folder)], "params_files": [], "output_dir": str(report_dir / folder_name)}
        jobs += [(n, report_dir / folder_name / n, one, _sequence_name(folder)) for n in PER_SEQUENCE_NOTEBOOKS]
    jobs += [(name, report_dir / name, dict(every), "") for name in PAPER_NOTEBOOKS]
    jobs += study_jobs(report_dir, output_dirs)
    executed = []
    bar = progress_bar(jobs, desc="analysis notebooks", unit="nb")
    for source, target, parameters, sequence in bar:
        bar.write(f"executing {source} -> {target}")
        item = execute_and_convert(source, target, parameters, sequence, index=report_dir / "index.html")
        if item.error:
            bar.write(f"  failed: {item.error} (see {target})")
        executed.append(item)
    index = atomic_write_text(report_dir / "index.html", summary_page(report_dir, output_dirs, executed))
    return index, executed


def run_folders(args: argparse.Namespace) -> list[Path]:
    """The OUTPUT_DIRs, else ``--outputs-root`` when it shows runs, else the output folders under it that do."""
    from gvbench_nb.evaluation import run_tables
    from gvbench_nb.runner.method_outputs import ResultsError

    example = "python -m gvbench_nb run params/sample.yaml writes one, outputs/sample"
    if args.output_dirs:
        absent = [d for d in args.output_dirs if not run_tables.shows_results(Path(d))]
        if absent:
            raise ResultsError(
                f"{', '.join(absent)} shows no finished run: give the output folder of a run ({example})"
            )
        return [Path(d) for d in args.output_dirs]
    root = Path(args.outputs_root)
    sequences = [s.strip() for s in args.sequences.split(",") if s.strip()] if args.sequences else None
    if not sequences and run_tables.shows_results(root):
        return [root]
    folders = [
        d for d in run_tables.find_output_dirs(root, sequences) if d.resolve() != Path(args.output_dir).resolve()
    ]
    if not folders:
        raise ResultsError(f"no output folder showing a finished run in or under {root} ({example})")
    return folders


def command_report(args: argparse.Namespace) -> int:
    output_dirs = run_folders(args)
    from gvbench_nb.evaluation import run_tables

    report_dir = Path(args.output_dir)
    run_tables.load_results(output_dirs)  # what `results` and the analysis notebooks refuse, before any file
    log.info(f"report over {len(output_dirs)} run folder(s): {', '.join(map(str, output_dirs))} -> {report_dir}")
    index, executed = write_report(report_dir, output_dirs)
    failed = [item for item in executed if item.error]
    log.info(f"report: {index}" + (f" ({len(failed)} notebook(s) failed, listed there)" if failed else ""))
    return 1 if failed else 0


def add_command(subparsers: argparse._SubParsersAction) -> None:
    """Register ``report`` on the CLI's subcommands."""
    parser = add_described_command(subparsers, "report", HELP, DESCRIPTION, EPILOG)
    parser.add_argument(
        "output_dirs",
        nargs="*",
        metavar="OUTPUT_DIR",
        help="output folders of finished runs, e.g. outputs/sample outputs/gardens_point "
        "(default: every such folder under --outputs-root)",
    )
    parser.add_argument(
        "--output-dir",
        default=str(config.PROJECT_ROOT / "outputs" / "report"),
        help="where the executed notebooks, their HTML, figures and index.html go (default: outputs/report)",
    )
    parser.add_argument(
        "--sequences",
        help="comma-separated sequence folder names under --outputs-root (default: every folder "
        "showing finished runs), e.g. sample,gardens_point",
    )
    parser.add_argument(
        "--outputs-root",
        default=str(config.PROJECT_ROOT / "outputs"),
        help="a folder holding run folders, or a run folder itself (default: outputs)",
    )
    parser.set_defaults(handler=command_report)
