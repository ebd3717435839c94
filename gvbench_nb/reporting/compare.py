"""``python -m gvbench_nb compare OUTPUT_DIR``: which method rankings a paired bootstrap over queries supports."""

from __future__ import annotations

import argparse
import json
import logging
from pathlib import Path

from gvbench_nb.io_utils import add_described_command, whole_number_at_least

log = logging.getLogger(__name__)

# `bootstrap` (and through it torch) is imported inside the handler: `--help` stays instant.

HELP = "AP and MR with bootstrap intervals over queries, and which method rankings a paired bootstrap supports"
DESCRIPTION = """\
Reads the pairs.csv of the runs an output folder shows (each method's latest run,
<output_dir>/runs/<id>/<method>/pairs.csv), or of several folders run on the same pairs
(nothing is recomputed), draws the
queries with replacement (every pair of a drawn query counts; the same draws for every method)
and prints each method's AP and MR with 95 % percentile intervals, then for every pair of
methods the share of those resamples in which the first (the higher on all pairs) beats the
second, is tied with it or loses. A pair is ranked when one side wins in at least 95 % of the
resamples; otherwise it is a tie. Methods scored on different pairs or labels are refused.
"""
EPILOG = """\
examples:
  python -m gvbench_nb compare outputs/gardens_point
  python -m gvbench_nb compare outputs/gardens_point --metric max_recall --resamples 2000 --seed 1 --markdown
  python -m gvbench_nb compare outputs/sample --methods sift-nn,xfeat-nn
  python -m gvbench_nb compare outputs/gardens_point outputs/gardens_point_xfeat_lg
"""


def resample_count(text: str) -> int:
    """argparse type of --resamples: a whole number of at least 100 (fewer makes 95 % percentiles coarse)."""
    return whole_number_at_least(text, 100, "a whole number of resamples of at least 100")


def command_compare(args: argparse.Namespace) -> int:
    from gvbench_nb.evaluation import bootstrap, collapsed_inliers, run_tables
    from gvbench_nb.reporting.tables import markdown_table
    from gvbench_nb.runner import method_outputs, scoring

    folders = [Path(f) for f in args.output_dirs]
    where = ", ".join(map(str, folders))
    methods = [m.strip() for m in args.methods.split(",") if m.strip()] if args.methods else None

    for folder in folders:
        scoring.readable_methods(folder)  # what `results` refuses, compare refuses
    tables = run_tables.load_pairs_tables(folders, methods)
    if len(tables) < 2:
        raise run_tables.IncomparableRunsError(
            f"{where} holds results of one method only ({', '.join(tables)}); "
            "run another method on the same pairs, or name two or more with --methods"
        )
    boot = bootstrap.bootstrap(tables, args.resamples, args.seed)
    found = run_tables.method_folders(folders)
    runs = {m: json.loads((method_outputs.method_dir(found[m], m) / "run.json").read_text()) for m in tables}
    table = bootstrap.intervals_of(boot)
    table.insert(1, "profile", [runs[m]["conf"]["profile"] for m in table["method"]])
    sequences = ", ".join(dict.fromkeys(run["sequence"] for run in runs.values()))
    show = lambda frame: markdown_table(frame) if args.markdown else frame.to_string(index=False, float_format="%.3f")
    log.info(
        f"{sequences} ({where}): AP and MR on all {boot.n_pairs} pairs, with 95 % percentile intervals over "
        f"{boot.n_queries} queries resampled with replacement ({args.resamples} resamples, seed {args.seed})\n"
    )
    columns = ["method", "profile", "ap", "ap_low", "ap_high", "max_recall", "max_recall_low", "max_recall_high"]
    print(show(table[columns]))
    for metric in [args.metric] if args.metric else list(run_tables.METRICS):
        log.info(
            f"\n{metric}: share of the same {args.resamples} query resamples in which the first beats the second "
            f"(tied: both equal); ranked when one side wins in >= {100 * bootstrap.RANKED_SHARE:.0f} % of them, "
            "else tie\n"
        )
        print(show(boot.paired_shares(metric)))
    for line in collapsed_inliers.collapse_warnings(tables):
        log.warning(f"\nwarning: {line}")
    return 0


def add_command(subparsers: argparse._SubParsersAction) -> None:
    """Register ``compare`` on the CLI's subcommands."""
    parser = add_described_command(subparsers, "compare", HELP, DESCRIPTION, EPILOG)
    parser.add_argument(
        "output_dirs",
        nargs="+",
        metavar="OUTPUT_DIR",
        help="output folders of finished runs on the same pairs, e.g. outputs/gardens_point "
        "(several: each method from the folder that has it)",
    )
    parser.add_argument(
        "--metric", choices=["ap", "max_recall"], help="rank by this metric only (default: both, AP first)"
    )
    parser.add_argument(
        "--resamples", type=resample_count, default=1000, help="query resamples (default 1000, at least 100)"
    )
    parser.add_argument("--seed", type=int, default=0, help="seed of the query draws (default 0)")
    parser.add_argument("--methods", help="comma-separated methods to compare (default: every finished one)")
    parser.add_argument("--markdown", action="store_true", help="print markdown tables (for docs)")
    parser.set_defaults(handler=command_compare)
