"""``python benchmarks/speed.py``: the bench (``speed_bench.py``) and its estimate (``speed_estimate.py``)."""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

import cv2
import pandas as pd
import speed_bench as bench
import speed_estimate as estimate

from gvbench_nb import methods as method_registry
from gvbench_nb.runner import concurrency
from gvbench_nb.runner.concurrency import add_jobs_argument


def build_parser() -> argparse.ArgumentParser:
    """``python benchmarks/speed.py``: the bench, a program of its own beside the package's CLI."""
    parser = argparse.ArgumentParser(
        prog="python benchmarks/speed.py",
        description="Time our cached pipeline against the per-pair reference pipeline on the same pairs: "
        "both run on the same pairs (cold cache in a temporary folder each repeat), the bench fails if any "
        "pair's num_inliers differ, and writes per-repeat, summary and scaling CSVs. With --estimate alone "
        "(no params), prints the official-sequence estimate from the summary.",
    )
    parser.add_argument(
        "--debug", action="store_true", help="show the full traceback of an error instead of its one-line message"
    )
    parser.add_argument("params", nargs="?", help="params YAML, e.g. params/gardens_point.yaml")
    parser.add_argument("--methods", help="comma-separated method names (default: the params')")
    parser.add_argument("--limit", type=int, help="only the first N pairs, as in `run` (default: every pair)")
    parser.add_argument("--repeats", type=int, default=3, help="repeats per method; medians reported (default 3)")
    parser.add_argument("--profile", help="'paper' or 'repository' (default: the params')")
    parser.add_argument("--device", help="override the params' device")
    parser.add_argument(
        "--threads",
        type=int,
        help="OpenCV threads for both pipelines, torch running on one (default: every core; on a loaded "
        "machine fewer threads than cores avoids spin-waiting, see the report)",
    )
    add_jobs_argument(
        parser,
        bench.DEFAULT_BENCH_JOBS,
        f"images or pairs our pipeline runs at once, as `run --jobs` (default here {bench.DEFAULT_BENCH_JOBS}; "
        "`run`'s is $GVBENCH_JOBS, else every core); the per-pair pipeline runs one pair at a time",
    )
    parser.add_argument(
        "--bench-dir", default=str(bench.DEFAULT_BENCH_DIR), help="where CSVs go (default outputs/bench)"
    )
    parser.add_argument(
        "--scaling",
        default=",".join(map(str, bench.DEFAULT_SCALING_LIMITS)),
        help="pair counts of the scaling table, or 'none' (default 50,100,200,400)",
    )
    parser.add_argument("--overlap", action="store_true", help="also measure whether prefetching hides decoding")
    parser.add_argument("--cprofile", action="store_true", help="also write a cProfile report of our pipeline")
    parser.add_argument("--estimate", action="store_true", help="print the official-sequence estimate at the end")
    parser.add_argument(
        "--runs",
        help="with --estimate: also cost every method that ran in this sequence output "
        "folder, from its per-pair timers (e.g. outputs/gardens_point)",
    )
    parser.add_argument(
        "--render",
        action="store_true",
        help="time rendering one synthetic query traversal, clear and under each condition at "
        "strength 1 (writes render.csv); needs no params",
    )
    parser.add_argument("--frames", type=int, default=100, help="frames of the --render traversal (default 100)")
    parser.set_defaults(handler=command_bench)
    return parser


def main(argv: list[str] | None = None) -> int:
    from gvbench_nb import cli

    return cli.main(argv, build_parser, "benchmarks/speed.py")


def command_bench(args: argparse.Namespace) -> int:
    import torch

    from gvbench_nb.data import fetch
    from gvbench_nb.protocol.features.base import resolve_device
    from gvbench_nb.runner import config, sequence_build

    bench_dir = Path(args.bench_dir)
    if args.estimate:  # before any timing: the estimate at the end would fail without them
        estimate.require_official_lists(fetch.data_dir() / "gvbench_gt")
    if args.render:
        bench.print_render_time(bench_dir, args.frames, args.repeats, args.threads)
    if args.params is None:
        if not (args.estimate or args.render):
            raise config.ParamsError("bench needs a params file (or --estimate or --render alone)")
        if args.estimate:
            estimate.print_estimate(bench_dir, runs=args.runs)
        return 0
    if args.repeats < 1:
        raise config.ParamsError(f"--repeats must be at least 1, got {args.repeats}")
    params = config.load_params(args.params, methods=args.methods, profile=args.profile, device=args.device)
    full = sequence_build.prepare_sequence(params)  # the limit applies below (scaling needs the longer prefix)
    sequence = full.limited(args.limit)
    concurrency.configure_threads(args.threads)
    profile, device, seed = params["profile"], params["device"], params["seed"]
    print(
        f"{sequence.name}: {len(sequence.pairs)} pairs, {len(sequence.images)} unique images, profile {profile}, "
        f"torch threads {torch.get_num_threads()}, OpenCV threads {cv2.getNumThreads()}, "
        f"{os.cpu_count()} CPUs, load average {os.getloadavg()[0]:.2f}"
    )
    for method in params["methods"]:
        rows = bench.bench_method(sequence, method, profile, args.repeats, device, seed, workers=args.jobs)
        bench.merge_csv(bench_dir / f"{sequence.name}_{method}.csv", rows, ["profile", "n_pairs"])
        summary = bench.summarize_bench(rows)
        bench.merge_csv(bench_dir / "summary.csv", summary, ["sequence", "method", "profile", "n_pairs"])
        bench.print_summary(summary)
        if args.scaling != "none":
            limits = tuple(int(v) for v in args.scaling.split(","))
            per_image = summary[f"{bench.PER_PAIR}_extract_seconds_per_pair"].iat[0] / 2
            scaling = bench.scaling_table(full, method, profile, limits, device, seed, per_image)
            bench.merge_csv(bench_dir / f"scaling_{sequence.name}_{method}.csv", scaling, ["profile", "n_pairs"])
            print(f"\nscaling ({method}, {profile}; stage sums of one cold run on {max(limits)} pairs):")
            print(
                scaling[
                    [
                        "n_pairs",
                        "n_images",
                        "uses_per_image",
                        "extract_seconds",
                        "match_seconds",
                        "verify_seconds",
                        "total_seconds",
                        "per_pair_total_seconds",
                        "speedup_from_stage_sums",
                    ]
                ].to_string(index=False, float_format=lambda v: f"{v:.3f}")
            )
        if args.overlap and not method_registry.is_dense(method_registry.resolve_method(method, profile)):
            overlap = pd.DataFrame([bench.measure_prefetch_overlap(sequence, method, profile, device)])
            bench.merge_csv(bench_dir / "overlap.csv", overlap, ["sequence", "method", "profile", "n_images"])
            print(
                "\nprefetch overlap:\n" + overlap.iloc[:, :9].to_string(index=False, float_format=lambda v: f"{v:.3f}")
            )
        if args.cprofile:
            report = bench.profile_pipeline(sequence, method, profile, device, seed)
            path = bench_dir / f"cprofile_{sequence.name}_{method}_{profile}.txt"
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_text(report)
            print(f"\ncProfile report: {path}")
    print(f"\nCSVs in {bench_dir}: {sequence.name}_<method>.csv, summary.csv, scaling_{sequence.name}_<method>.csv")
    if args.estimate:
        print()
        estimate.print_estimate(bench_dir, runs=args.runs)
    else:
        print(bench.GPU_NOTE if resolve_device(device).type != "cuda" else "")
    return 0


if __name__ == "__main__":
    sys.exit(main())
