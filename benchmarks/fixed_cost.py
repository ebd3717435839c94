"""The fixed cost of ``python -m gvbench_nb run``: wall time of a small run, each time in a
fresh output and cache folder, and where it goes (before the first notebook, each notebook's
kernel and cells, after the last), read from the executed notebooks' papermill metadata.

    python benchmarks/fixed_cost.py params/sample.yaml --methods sift-nn --limit 4 --repeats 3
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

PROJECT = Path(__file__).resolve().parent.parent


def _time(text: str) -> float:
    return dt.datetime.fromisoformat(text).timestamp()


def notebook_times(path: Path) -> dict[str, Any]:
    """Start, end, duration, the setup (import) cell's and all cells' seconds of an executed notebook."""
    notebook = json.loads(path.read_text(encoding="utf-8"))
    meta = notebook["metadata"]["papermill"]
    cells = [c for c in notebook["cells"] if c["cell_type"] == "code"]
    seconds = [c["metadata"].get("papermill", {}).get("duration") or 0.0 for c in cells]
    setup = next((s for c, s in zip(cells, seconds) if "from gvbench_nb import" in "".join(c["source"])), 0.0)
    return {
        "start": _time(meta["start_time"]),
        "end": _time(meta["end_time"]),
        "duration": meta["duration"],
        "cells": sum(seconds),
        "setup": setup,
    }


def one_run(params: str, methods: str, limit: int, keep: Path | None) -> dict[str, Any]:
    folder = Path(tempfile.mkdtemp(prefix="fixed_cost_", dir=keep))
    out = folder / "out"  # and its cache folder/cache (GVBENCH_CACHE below): fresh too
    command = [
        sys.executable,
        "-m",
        "gvbench_nb",
        "run",
        params,
        "--methods",
        methods,
        "--limit",
        str(limit),
        "--output-dir",
        str(out),
    ]
    environment = {**os.environ, "PYTHONPATH": str(PROJECT), "GVBENCH_CACHE": str(folder / "cache")}
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    started = time.time()
    done = subprocess.run(command, cwd=PROJECT, env=environment, capture_output=True, text=True)
    ended = time.time()
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    # CPU seconds of the command and every kernel it started: steadier than wall time on shared cores.
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    notebooks = {p.stem: notebook_times(p) for p in sorted(out.glob("0*.ipynb"))}
    first = min(n["start"] for n in notebooks.values()) if notebooks else ended
    last = max(n["end"] for n in notebooks.values()) if notebooks else ended
    return {
        "started": started,
        "wall": ended - started,
        "cpu": cpu,
        "rc": done.returncode,
        "before_notebooks": first - started,
        "notebooks_wall": last - first,
        "after_notebooks": ended - last,
        "notebooks": notebooks,
        "stderr": done.stderr[-2000:],
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("params", help="params YAML, e.g. params/sample.yaml")
    parser.add_argument("--methods", default="sift-nn")
    parser.add_argument("--limit", type=int, default=4)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--keep", type=Path, default=None, help="make the run folders under this folder")
    args = parser.parse_args()
    runs = []
    for repeat in range(args.repeats):
        run = one_run(args.params, args.methods, args.limit, args.keep)
        runs.append(run)
        # Each notebook's seconds, its kernel and papermill's share, and when it ran (from the command's start).
        parts = "\n  ".join(
            f"{name} {n['duration']:.1f}s (kernel+papermill {n['duration'] - n['cells']:.1f}, "
            f"setup cell {n['setup']:.1f}; from {n['start'] - run['started']:.1f} "
            f"to {n['end'] - run['started']:.1f})"
            for name, n in run["notebooks"].items()
        )
        print(
            f"run {repeat + 1}: wall {run['wall']:.1f}s cpu {run['cpu']:.1f}s rc {run['rc']}  "
            f"before notebooks {run['before_notebooks']:.1f}s  notebooks {run['notebooks_wall']:.1f}s  "
            f"after {run['after_notebooks']:.1f}s\n  {parts}",
            flush=True,
        )
        if run["rc"] != 0:
            print(run["stderr"])
    median = lambda key: statistics.median(r[key] for r in runs)
    print(
        f"median of {len(runs)}: wall {median('wall'):.1f}s, cpu {median('cpu'):.1f}s, "
        f"before notebooks {median('before_notebooks'):.1f}s, notebooks {median('notebooks_wall'):.1f}s, "
        f"after {median('after_notebooks'):.1f}s (load average at the end {os.getloadavg()[0]:.1f} "
        f"on {os.cpu_count()} cores)"
    )


if __name__ == "__main__":
    main()
