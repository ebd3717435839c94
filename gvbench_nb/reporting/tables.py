"""Tables as text for a terminal or a README: ``python -m gvbench_nb results``."""

from __future__ import annotations

import argparse
import contextlib
import logging
import textwrap
from pathlib import Path
from typing import Any

log = logging.getLogger(__name__)

HEADER_WIDTH = 100  # the machine's line above a table, as a terminal of 100 columns shows it
# Every column of `results --wide` and `--markdown` (the README's tables come from the latter).
WIDE_COLUMNS = [
    *["method", "paper_name", "profile", "n_pairs", "n_positives"],
    *["ap", "ap_low", "ap_high", "max_recall", "max_recall_low", "max_recall_high"],
    *["extract_seconds_per_pair", "match_seconds_per_pair", "verify_seconds_per_pair", "seconds_per_pair"],
    *["timers", "pairs_digest"],
]


def markdown_table(frame: Any) -> str:
    """A pandas frame as a GitHub markdown table (floats to 3 decimals)."""
    header = "| " + " | ".join(map(str, frame.columns)) + " |"
    rule = "|" + "|".join("---" for _ in frame.columns) + "|"
    cell = lambda v: f"{v:.3f}" if isinstance(v, float) else str(v)
    rows = ["| " + " | ".join(cell(v) for v in row) + " |" for row in frame.itertuples(index=False)]
    return "\n".join([header, rule, *rows])


def compact_table(results: Any) -> Any:
    """The results in the columns a terminal of 100 fits: method, profile, pairs, AP and MR with
    their 95 % intervals, seconds a pair (marked ``*`` where the timers are not all this run's;
    'imported' for scores computed elsewhere, which have none)."""
    import pandas as pd

    def with_interval(metric: str) -> list[str]:
        columns = zip(results[metric], results[f"{metric}_low"], results[f"{metric}_high"])
        return [f"{value:.3f} [{low:.3f}, {high:.3f}]" for value, low, high in columns]

    seconds = [
        "imported" if t == "imported" else f"{s:.3f}" + ("" if t == "this run" else "*")
        for s, t in zip(results["seconds_per_pair"], results["timers"])
    ]
    return pd.DataFrame(
        {
            "method": results["method"],
            "profile": results["profile"],
            "n_pairs": results["n_pairs"],
            "AP [95% CI]": with_interval("ap"),
            "MR [95% CI]": with_interval("max_recall"),
            "s/pair": seconds,
        }
    )


def results_header(folder: Path, results: Any, runs: list[dict[str, Any]]) -> str:
    """Lines above a folder's table: the sequence and the folder; when, and --limit; the machine and libraries."""
    measured = [run for run in runs if "imported" not in run]  # imported scores say nothing of this machine
    finished = max(run["finished_at"] for run in runs)
    limits = sorted({int(limit) for run in runs if (limit := (run.get("pairs") or {}).get("limit")) is not None})
    cut = f", the first {', '.join(map(str, limits))} pairs (--limit)" if limits else ""
    machine = "imported scores only"
    if measured:
        env = measured[0]["environment"]
        libraries = f", {env['cpu_count']} cores), torch {env['torch']}, kornia {env['kornia']}, opencv {env['opencv']}"
        room = HEADER_WIDTH - len(f"device {env['device']} ({libraries}")  # a long CPU name is cut to fit
        name = textwrap.shorten(env["device_name"], max(room, 8), placeholder="...")
        machine = f"device {env['device']} ({name}{libraries}"
    return f"{results['sequence'].iloc[0]} in {folder}\nruns finished {finished}{cut}\n{machine}\n"


def command_results(args: argparse.Namespace) -> int:
    from gvbench_nb.evaluation import bootstrap, collapsed_inliers
    from gvbench_nb.runner import method_outputs, runs, scoring

    for folder in map(Path, args.output_dirs):
        if args.run is not None:  # an earlier run, by its whole id
            folder = runs.find_run(folder, args.run)
        results = scoring.evaluate(folder, scoring.readable_methods(folder), write=False)
        if args.run is None:  # the folder's table for people, made again (a folder not ours to write keeps its own)
            with contextlib.suppress(OSError):
                scoring.refresh_view(folder)
        pair_tables = {m: scoring.load_pairs_table(folder, m) for m in results["method"]}
        results = results.join(bootstrap.interval_columns(pair_tables), on="method")
        records = [method_outputs.read_run_json(folder, m) for m in results["method"]]
        collapse_warnings = collapsed_inliers.collapse_warnings(pair_tables)
        print(results_header(folder, results, records))
        if args.markdown:
            print(markdown_table(results[WIDE_COLUMNS]))
        else:
            table = results[WIDE_COLUMNS] if args.wide else compact_table(results)
            print(table.to_string(index=False, float_format="%.3f"))
        log.info(
            f"\n{'*_low, *_high' if args.markdown or args.wide else 'CI'}: 95 % bootstrap interval over "
            f"{results['interval_unit'].iloc[0]} resamples (`compare` ranks the methods pairwise)"
        )
        reused = results.loc[~results["timers"].isin(["this run", "imported"]), ["method", "timers"]]
        if len(reused) and not (args.markdown or args.wide):
            log.info(
                "*: seconds from the cache, the runs' that computed them: "
                + ", ".join(f"{m} ({t})" for m, t in zip(reused["method"], reused["timers"]))
            )
        print()
        for line in scoring.left_out(folder):
            log.warning(f"not in this table: {line}")
        for line in collapse_warnings:
            log.warning(f"warning: {line}")
        if leftovers := runs.leftovers(runs.output_folder(folder)):
            log.warning(leftovers)
        if args.export == "npy":
            from gvbench_nb.runner import score_files

            for row in results["method"]:
                method = runs.method_folder(folder, row)  # a row's run: the method's folder there
                path, ap = score_files.export_npy(method.parent, method.name)
                log.info(f"{row}: {path} (AP {ap:.4f})")
        if args.all_methods:
            others = not_run_table(set(results["method"]))
            if len(others):
                print(f"registered methods without results in {folder}:\n")
                print(markdown_table(others) if args.markdown else others.to_string(index=False))
                print()
    return 0


def not_run_table(ran: set[str]) -> Any:
    """Registered methods that have no results: why, and the files a user needs to run them."""
    import pandas as pd

    from gvbench_nb import methods
    from gvbench_nb.protocol import weights

    rows = []
    for row in methods.method_table():
        if row["method"] in ran:
            continue
        missing = [c for c in methods.required_checkpoints(row["method"]) if not weights.is_present(c)]
        needs = "; ".join(f"`{weights.get(c).file}` from {weights.get(c).urls[0]}" for c in missing)
        rows.append(
            {
                "method": row["method"],
                "paper_name": row["paper_name"],
                "status": f"not run here: needs {needs}" if missing else "weights present, not run",
            }
        )
    return pd.DataFrame(rows, columns=["method", "paper_name", "status"])


def command_import_scores(args: argparse.Namespace) -> int:
    from gvbench_nb.runner import score_files

    row = score_files.import_scores(args.file, args.sequence, args.method, args.output_dir, args.image_root)
    print(
        f"{args.method}: {row['n_pairs']} pairs ({row['n_positives']} true), AP {row['ap']:.4f}, "
        f"MR {row['max_recall']:.4f} -> run {row['run']} of {args.output_dir}"
    )
    earlier = row["earlier"]
    if earlier is not None:
        print(
            f"{args.output_dir} now shows run {row['run']} (imported) for {args.method}; its earlier run "
            f"{earlier.run.name} is kept: python -m gvbench_nb results {args.output_dir} --run {earlier.run.name}"
        )
    for key, value in row["stated"].items():
        print(f"  the file states {key} {value:.4f} (recomputed here from its pairs: {row[key]:.4f})")
    return 0


def command_upgrade(args: argparse.Namespace) -> int:
    from gvbench_nb.runner import runs, scoring

    print(runs.upgrade(args.output_dir))
    scoring.refresh_view(Path(args.output_dir))
    return 0


def command_clean(args: argparse.Namespace) -> int:
    from gvbench_nb.runner import runs

    removed, kept = runs.clean(args.output_dir, args.superseded)
    print(f"{args.output_dir}: removed {len(removed)} (" + (", ".join(removed) or "nothing to remove") + ")")
    if kept:
        log.info(f"kept {len(kept)} unfinished runs whose process is still running: {', '.join(kept)}")
    return 0


def add_command(commands: Any) -> None:
    """Register ``results`` (``--export npy``: per-pair scores out) and ``import-scores FILE`` (in)."""
    results = commands.add_parser(
        "results", help="print the results table of finished runs (from their pairs.csv, nothing recomputed)"
    )
    results.add_argument("output_dirs", nargs="+", help="sequence output folders, e.g. outputs/gardens_point")
    results.add_argument(
        "--wide", action="store_true", help="every column: paper names, positives, seconds by stage, timers, digest"
    )
    results.add_argument(
        "--markdown", action="store_true", help="print a markdown table of every column (for a README)"
    )
    results.add_argument(
        "--all-methods",
        action="store_true",
        help="also list every registered method without results, with the weight files it needs",
    )
    results.add_argument(
        "--run", metavar="ID", help="the table of one earlier run of the folder (its whole id, a folder under runs/)"
    )
    results.set_defaults(handler=command_results)
    parser = commands.add_parser(
        "import-scores",
        help="publish per-pair scores computed elsewhere as a method of an output folder",
        description="Read the GV-Bench authors' per-pair .npy ($seq_$feature_$match.npy) or a table "
        "'query reference label score' (CSV or whitespace, header optional) and publish it as METHOD in "
        "OUTPUT_DIR, beside methods scored on the same pairs and labels; results, compare and report read "
        "it like a run. Its run.json names the file and its SHA-256. The format is read from the file's "
        "content, not its name; a .npy pickling anything but plain data is refused without running it. Its pairs "
        "are checked as a pair file's are. An import under the name of a method OUTPUT_DIR already shows adds a "
        "run and changes no byte of the other: the folder shows the import (its latest run for that method), and "
        "the command names the other run's `results OUTPUT_DIR --run ID`.",
    )
    upgrade = commands.add_parser(
        "upgrade",
        help="take the results of a folder written by an earlier gvbench-nb in as a run",
        description="Copy each method's pairs.csv and run.json of a folder in the earlier layout (gvbench-run.json "
        "at its top) into one new run under runs/; nothing is deleted or changed.",
    )
    upgrade.add_argument("output_dir", help="the folder, e.g. outputs/gardens_point")
    upgrade.set_defaults(handler=command_upgrade)
    clean = commands.add_parser(
        "clean",
        help="remove an output folder's unfinished runs whose process has ended (runs/.building-*)",
        description="Remove the runs/.building-* folders that failed, killed or interrupted runs left, once the "
        "process that started each has ended (a build started on another machine: once nothing in it changed for a "
        "day); a finished run is removed only with --superseded.",
    )
    clean.add_argument("output_dir", help="the output folder, e.g. outputs/gardens_point")
    clean.add_argument(
        "--superseded", action="store_true", help="also remove the finished runs the folder's table no longer shows"
    )
    clean.set_defaults(handler=command_clean)
    parser.add_argument("file", help="the .npy or the table of scores")
    parser.add_argument("--sequence", required=True, help="the sequence's name in tables and plots, e.g. night")
    parser.add_argument("--method", required=True, help="the method's name (its folder), e.g. sp-sg-authors")
    parser.add_argument("--output-dir", required=True, help="the output folder to publish it in")
    parser.add_argument(
        "--image-root",
        help="the folder the pairs' paths are relative to: each image must be there, and a pair of two images "
        "with one content is refused (without it no image is read)",
    )
    parser.set_defaults(handler=command_import_scores)
    results.add_argument(
        "--export",
        choices=["npy"],
        help="also write the pairs of each method's shown run as the GV-Bench authors' "
        "<output_dir>/exports/<sequence>_<method>_<run id>.npy",
    )
