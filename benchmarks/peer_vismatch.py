"""Ours against the peer: our pipeline and vismatch's own per-pair loop, same pairs, same resolution.

The peer is what the GV-Bench repository runs (image-matching-models, ``vismatch`` on PyPI): for
every pair, load both images, extract both, match, RANSAC (``matcher(img0, img1)``). It runs in
the opt-in venv (``make setup-imm``); ours runs in the default venv as a user runs it
(``python -m gvbench_nb run``, notebooks included, a fresh cache every run). Both are timed as
whole processes, alternating (ours, peer, ours, peer, ...), and compared by the ratio of their
median wall times. AP and MR of both come from the same metric code (``gvbench_nb.protocol.metrics``).

    .venv/bin/python benchmarks/peer_vismatch.py params/gardens_point.yaml --method sift-nn --runs 2

writes ``<out>/peer_runs.csv`` (one row a process) and ``<out>/peer_summary.csv``, and prints the
summary. ``--limit N`` runs the first N pairs only.
"""

from __future__ import annotations

import argparse
import csv
import os
import shutil
import statistics
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parent.parent

# Our method -> the vismatch matcher that does the same thing.
PEER_NAMES = {
    "sift-nn": "sift-nn",
    "orb-nn": "orb-nn",
    "disk-lg": "disk-lightglue",
    "aliked-lg": "aliked-lightglue",
    "sp-lg": "superpoint-lightglue",
    "xfeat-lg": "xfeat-lightglue",
    "loftr": "loftr",
}


def run_process(command: list[str], log: Path, env: dict[str, str]) -> tuple[float, float, int]:
    """Wall seconds, peak resident MiB (of the process or the largest child it waited for), exit code."""
    start = time.perf_counter()
    with open(log, "w") as handle:
        process = subprocess.Popen(command, stdout=handle, stderr=subprocess.STDOUT, cwd=REPO, env=env)
        _, status, usage = os.wait4(process.pid, 0)
    wall = time.perf_counter() - start
    process.returncode = os.waitstatus_to_exitcode(status)
    return wall, usage.ru_maxrss / 1024.0, process.returncode


def write_pair_file(sequence: Any, path: Path) -> None:
    with open(path, "w") as handle:
        for pair in sequence.pairs:
            handle.write(f"{pair.query} {pair.reference} {pair.label}\n")


def peer_image_size(params: dict[str, Any], method: str, sequence: Any) -> tuple[int, int]:
    """(height, width) our profile prepares this sequence's images at (its first image decides)."""
    from gvbench_nb import methods
    from gvbench_nb.protocol.images import read_image, target_size

    conf = methods.resolve_method(method, params["profile"])
    prepared = conf["extractor"] or conf["matcher"]
    height, width = read_image(sequence.image_root / sequence.pairs[0].query).shape[:2]
    size = target_size(
        width,
        height,
        prepared.get("resize_max"),
        prepared.get("resize_force", False),
        prepared.get("multiple_of"),
        prepared.get("resize_to"),
    )
    return size[1], size[0]


def score_pairs(labels: list[int], scores: list[float]) -> dict[str, float]:
    from gvbench_nb.protocol.metrics import evaluate_scores

    metrics = evaluate_scores(labels, scores, where="peer")
    return {"ap": metrics["ap"], "max_recall": metrics["max_recall"]}


def orchestrate(args: argparse.Namespace) -> int:
    from gvbench_nb.runner import config, method_outputs, sequence_build

    ours_python, peer_python = Path(args.ours_python), Path(args.peer_python)
    for what, path, hint in (("ours", ours_python, "make setup"), ("peer", peer_python, "make setup-imm")):
        if not path.is_file():
            print(
                f"error: the {what} Python {path} does not exist; create it with `{hint}` or pass --{what}-python",
                file=sys.stderr,
            )
            return 2
    if args.method not in PEER_NAMES:
        print(
            f"error: no vismatch counterpart of {args.method!r}; choose one of {', '.join(PEER_NAMES)}", file=sys.stderr
        )
        return 2
    params = config.load_params(args.params, limit=args.limit, profile=args.profile)
    sequence = sequence_build.prepare_sequence(params)
    out = Path(args.out).resolve()
    out.mkdir(parents=True, exist_ok=True)
    pair_file = out / "pairs.txt"
    write_pair_file(sequence, pair_file)
    height, width = peer_image_size(params, args.method, sequence)
    peer_name = args.peer_matcher or PEER_NAMES[args.method]
    env = {**os.environ, "PYTHONPATH": str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", "")}
    print(
        f"{sequence.name}: {len(sequence.pairs)} pairs, {len(sequence.images)} images; ours {args.method} "
        f"(profile {params['profile']}) vs vismatch {peer_name} at {width}x{height}, {args.runs} runs each -> {out}"
    )

    rows: list[dict[str, Any]] = []
    for run in range(args.runs):
        for side in ("ours", "peer"):
            folder = out / f"{side}_{run}"
            shutil.rmtree(folder, ignore_errors=True)
            folder.mkdir()
            if side == "ours":  # a fresh output and cache folder: nothing is reused between runs
                command = [
                    str(ours_python),
                    "-m",
                    "gvbench_nb",
                    "run",
                    str(Path(args.params).resolve()),
                    "--methods",
                    args.method,
                    "--output-dir",
                    str(folder / "output"),
                ]
                env["GVBENCH_CACHE"] = str(folder / "cache")
                command += ["--limit", str(args.limit)] if args.limit else []
                command += ["--profile", args.profile] if args.profile else []
            else:
                command = [
                    str(peer_python),
                    str(Path(__file__).resolve()),
                    "--peer-loop",
                    "--pairs",
                    str(pair_file),
                    "--image-root",
                    str(sequence.image_root),
                    "--matcher",
                    peer_name,
                    "--size",
                    str(height),
                    str(width),
                    "--max-keypoints",
                    str(args.peer_max_keypoints),
                    "--scores",
                    str(folder / "scores.csv"),
                ]
            wall, peak, code = run_process(command, folder / "log.txt", env)
            if code != 0:
                print(
                    f"error: {side} run {run} exited with {code}; its output is in {folder / 'log.txt'}",
                    file=sys.stderr,
                )
                return 1
            if side == "ours":
                import pandas as pd

                table = pd.read_csv(method_outputs.method_dir(folder / "output", args.method) / "pairs.csv")
                labels, scores = table["label"].tolist(), table["score"].tolist()
            else:
                with open(folder / "scores.csv") as handle:
                    read = list(csv.DictReader(handle))
                labels, scores = [int(r["label"]) for r in read], [float(r["num_inliers"]) for r in read]
            rows.append(
                {
                    "run": run,
                    "side": side,
                    "method": args.method if side == "ours" else f"vismatch:{peer_name}",
                    "n_pairs": len(labels),
                    "wall_seconds": round(wall, 2),
                    "peak_rss_mib": round(peak, 1),
                    **score_pairs(labels, scores),
                }
            )
            print(
                f"  run {run} {side}: {wall:.1f} s, peak {peak:.0f} MiB, AP {rows[-1]['ap']:.3f}, "
                f"MR {rows[-1]['max_recall']:.3f}"
            )

    with open(out / "peer_runs.csv", "w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    summary = []
    for side in ("ours", "peer"):
        mine = [r for r in rows if r["side"] == side]
        summary.append(
            {
                "side": side,
                "method": mine[0]["method"],
                "n_pairs": mine[0]["n_pairs"],
                "runs": len(mine),
                "median_wall_seconds": statistics.median(r["wall_seconds"] for r in mine),
                "max_peak_rss_mib": max(r["peak_rss_mib"] for r in mine),
                "ap": mine[-1]["ap"],
                "max_recall": mine[-1]["max_recall"],
            }
        )
    ratio = summary[1]["median_wall_seconds"] / summary[0]["median_wall_seconds"]
    for row in summary:
        row["peer_over_ours"] = round(ratio, 3)
    with open(out / "peer_summary.csv", "w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=list(summary[0]))
        writer.writeheader()
        writer.writerows(summary)
    ours, peer = summary
    print(
        f"\nours {ours['method']}: median {ours['median_wall_seconds']:.1f} s, AP {ours['ap']:.3f}, "
        f"MR {ours['max_recall']:.3f}\npeer {peer['method']}: median {peer['median_wall_seconds']:.1f} s, "
        f"AP {peer['ap']:.3f}, MR {peer['max_recall']:.3f}\npeer / ours wall time {ratio:.2f}x "
        f"({'ours' if ratio > 1 else 'the peer'} faster; ratio of medians, {args.runs} alternating runs each)\n{out / 'peer_runs.csv'}\n{out / 'peer_summary.csv'}"
    )
    return 0


def peer_loop(args: argparse.Namespace) -> int:
    """vismatch's own loop, as the GV-Bench repository's main.py runs it: per pair, load both
    images (its loader, resized to --size), then matcher(img0, img1); the score is num_inliers."""
    from vismatch import get_matcher
    from vismatch.base_matcher import BaseMatcher

    matcher = get_matcher(args.matcher, device=args.device, max_num_keypoints=args.max_keypoints)
    root, size = Path(args.image_root), tuple(args.size)
    with open(args.pairs) as handle:
        pairs = [line.split() for line in handle if line.strip()]
    with open(args.scores, "w", newline="") as handle:
        writer = csv.writer(handle)
        writer.writerow(["query", "reference", "label", "num_inliers"])
        for query, reference, label in pairs:
            image0 = BaseMatcher.load_image(root / query, resize=size)
            image1 = BaseMatcher.load_image(root / reference, resize=size)
            writer.writerow([query, reference, label, matcher(image0, image1)["num_inliers"]])
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument(
        "params", nargs="?", help="params YAML (the sequence and pairs), e.g. params/gardens_point.yaml"
    )
    parser.add_argument("--method", default="sift-nn", help=f"our method, one of {', '.join(PEER_NAMES)}")
    parser.add_argument("--profile", help="our profile (default: the params'); the peer runs at its image size")
    parser.add_argument("--limit", type=int, help="only the first N pairs")
    parser.add_argument("--runs", type=int, default=2, help="alternating runs of each side (default 2)")
    parser.add_argument("--out", default=str(REPO / "outputs" / "peer_bench"), help="folder for logs and CSVs")
    parser.add_argument("--ours-python", default=str(REPO / ".venv" / "bin" / "python"))
    parser.add_argument("--peer-python", default=str(REPO / ".venv-imm" / "bin" / "python"))
    parser.add_argument("--peer-matcher", help="vismatch matcher name (default: the counterpart of --method)")
    parser.add_argument(
        "--peer-max-keypoints", type=int, default=2048, help="vismatch's keypoint budget (its default 2048)"
    )
    # The peer process (run by the orchestrator in the vismatch venv).
    parser.add_argument("--peer-loop", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--pairs", help=argparse.SUPPRESS)
    parser.add_argument("--image-root", help=argparse.SUPPRESS)
    parser.add_argument("--matcher", help=argparse.SUPPRESS)
    parser.add_argument("--size", type=int, nargs=2, help=argparse.SUPPRESS)
    parser.add_argument("--max-keypoints", type=int, default=2048, help=argparse.SUPPRESS)
    parser.add_argument("--device", default="cpu", help=argparse.SUPPRESS)
    parser.add_argument("--scores", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.peer_loop:
        return peer_loop(args)
    if not args.params:
        parser.error("give a params file, e.g. params/gardens_point.yaml")
    if args.runs < 1:
        parser.error("--runs must be at least 1")
    return orchestrate(args)


if __name__ == "__main__":
    sys.path.insert(0, str(REPO))
    sys.exit(main())
