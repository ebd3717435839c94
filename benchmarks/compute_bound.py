"""How fast a run could be on N cores: the protocol's own compute, measured one core at a time.

Runs ``python -m gvbench_nb run PARAMS --methods M`` once with one job on one thread
(``GVBENCH_JOBS=1 GVBENCH_THREADS=1``, a fresh output and cache folder), so that each image's
extraction timer and each pair's match and verify timers are that item's cost on one core. Their
sum is the work the protocol needs (SIFT or ORB extraction of every image, the descriptor
distances and RANSAC of every pair); divided by the cores, it bounds the wall time of any run of
that protocol on those cores, before decoding, storage, the notebooks and the fixed cost are
counted. With ``--peer-seconds`` (vismatch's median wall time from ``peer_vismatch.py``) it prints
the largest speed-up over the peer those cores allow.

    .venv/bin/python benchmarks/compute_bound.py params/gardens_point.yaml --method sift-nn --cores 2 --peer-seconds 310

writes ``<out>/compute_bound.csv`` (one row) and prints it.
"""

from __future__ import annotations

import argparse
import csv
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
TIMERS = ("extract_seconds", "match_seconds", "verify_seconds")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("params", help="a params file, e.g. params/gardens_point.yaml")
    parser.add_argument("--method", default="sift-nn")
    parser.add_argument("--profile", help="default: the params'")
    parser.add_argument("--limit", type=int, help="only the first N pairs")
    parser.add_argument("--cores", type=int, default=len(os.sched_getaffinity(0)), help="default: this machine's")
    parser.add_argument("--peer-seconds", type=float, help="the peer's median wall time on the same pairs")
    parser.add_argument("--out", default=str(REPO / "outputs" / "compute_bound"), help="folder for the run and CSV")
    args = parser.parse_args(argv)

    import pandas as pd

    out = Path(args.out).resolve()
    shutil.rmtree(out / "run", ignore_errors=True)
    out.mkdir(parents=True, exist_ok=True)
    command = [sys.executable, "-m", "gvbench_nb", "run", str(Path(args.params).resolve()), "--methods", args.method]
    command += ["--output-dir", str(out / "run" / "output")]
    command += ["--profile", args.profile] if args.profile else []
    command += ["--limit", str(args.limit)] if args.limit else []
    env = {**os.environ, "GVBENCH_JOBS": "1", "GVBENCH_THREADS": "1", "OMP_NUM_THREADS": "1"}
    env["GVBENCH_CACHE"] = str(out / "run" / "cache")  # emptied above: every image extracted by this run
    start = time.perf_counter()
    with open(out / "run.log", "w") as log:
        code = subprocess.call(command, stdout=log, stderr=subprocess.STDOUT, cwd=REPO, env=env)
    wall = time.perf_counter() - start
    if code != 0:
        print(f"error: the one-core run exited with {code}; its output is in {out / 'run.log'}", file=sys.stderr)
        return 1
    from gvbench_nb.runner import method_outputs

    table = pd.read_csv(method_outputs.method_dir(out / "run" / "output", args.method) / "pairs.csv")
    sums = {name: float(table[name].sum()) for name in TIMERS}  # extract_seconds shares each image over its pairs
    work = sum(sums.values())
    row = {
        "method": args.method,
        "n_pairs": len(table),
        **{f"{name}_total": round(value, 2) for name, value in sums.items()},
        "one_core_work_seconds": round(work, 2),
        "one_core_run_wall_seconds": round(wall, 2),
        "cores": args.cores,
        "bound_wall_seconds": round(work / args.cores, 2),
    }
    if args.peer_seconds:
        row["peer_wall_seconds"] = args.peer_seconds
        row["largest_speedup_over_peer"] = round(args.peer_seconds / (work / args.cores), 2)
    with open(out / "compute_bound.csv", "w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=list(row))
        writer.writeheader()
        writer.writerow(row)
    for key, value in row.items():
        print(f"{key}: {value}")
    print(out / "compute_bound.csv")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
