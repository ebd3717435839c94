"""Runs at the official sequences' size: wall time, peak memory and disk of ``python -m gvbench_nb
run`` on 2,000, 8,000 and 34,400 pairs (an official day/night/season/weather sequence's count) built
from Gardens Point's 600 frames, each size and method from an empty cache.

The rule (``official_size_pairs``): queries are every frame of ``night_right`` and ``day_left``,
references every frame of ``day_right`` (two traversals against a third). A pair is true when the
frame numbers differ by at most 2 (``tolerance`` of params/gardens_point.yaml) and false when they
differ by 6 or more (its ``negative_margin``); pairs 3-5 frames apart are never drawn. These 77,648
candidates are shuffled once (``random.Random(seed)``, seed 0); the N-pair sequence is the first N of
that shuffle, written sorted by query then reference. So the sizes are nested subsets (2,000 within
8,000 within 34,400) and about 2.6 % of each are true pairs (1,988 of the 77,648 candidates).

    nice -n 19 python benchmarks/official_size.py --sizes 2000,8000,34400 --methods orb-nn,sift-nn --kill-at 0.5

writes ``<out>/pairs/official_size_<N>.txt`` and ``<out>/params/official_size_<N>.yaml``, runs each
into ``<out>/runs/<N>_<method>/`` (output and cache), and prints and writes ``<out>/official_size.csv``
(rows of the same size and method replaced). Peak memory is the largest sum of resident memory over
the run's process tree (the run, its workers and notebook kernels) and that of its largest process, polled every 0.2 s. With
``--kill-at F`` the largest size's first method runs again from an empty cache, is killed (SIGKILL
to its process group) once its match store holds F of the pairs, is rerun with the same command, and
its per-pair table and results are compared with the uninterrupted run's, timers aside.
"""

from __future__ import annotations

import argparse
import os
import random
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pandas as pd
import psutil
import speed_bench as bench
import speed_estimate as estimate

from gvbench_nb.data import fetch
from gvbench_nb.data.sequences import Pair, frame_index, write_pairs
from gvbench_nb.runner import method_outputs

REPO = Path(__file__).resolve().parent.parent
QUERY_FOLDERS, REFERENCE_FOLDER = ("night_right", "day_left"), "day_right"
TOLERANCE, NEGATIVE_MARGIN = 2, 6  # params/gardens_point.yaml's
KEYS = ["n_pairs", "method"]


def official_size_pairs(root: Path, n_pairs: int, frames: int | None = None, seed: int = 0) -> list[Pair]:
    """The first ``n_pairs`` of the seeded shuffle of every candidate (the module's rule), sorted."""
    names = {folder: sorted(p.name for p in (root / folder).glob("*.jpg"))[:frames] for folder in os.listdir(root)}
    candidates = [
        Pair(f"{q_folder}/{q}", f"{REFERENCE_FOLDER}/{r}", int(abs(frame_index(q) - frame_index(r)) <= TOLERANCE))
        for q_folder in QUERY_FOLDERS
        for q in names[q_folder]
        for r in names[REFERENCE_FOLDER]
        if not TOLERANCE < abs(frame_index(q) - frame_index(r)) < NEGATIVE_MARGIN
    ]
    if n_pairs > len(candidates):
        raise SystemExit(f"error: --sizes asks for {n_pairs} pairs, but the rule has {len(candidates)}; ask fewer")
    random.Random(seed).shuffle(candidates)
    return sorted(candidates[:n_pairs], key=lambda pair: (pair.query, pair.reference))


def write_sequence(out: Path, root: Path, n_pairs: int, frames: int | None) -> Path:
    """Pair file and params file of the N-pair sequence; returns the params file."""
    pairs = write_pairs(out / "pairs" / f"official_size_{n_pairs}.txt", official_size_pairs(root, n_pairs, frames))
    params = out / "params" / f"official_size_{n_pairs}.yaml"
    params.parent.mkdir(parents=True, exist_ok=True)
    params.write_text(
        f"sequence: official_size_{n_pairs}\n"
        f"description: Gardens Point, {n_pairs} pairs by benchmarks/official_size.py's rule\n"
        f"image_root: {root}\npairs: {pairs}\nmethods: [sift-nn]\nprofile: repository\n"
        f"output_dir: {out / 'runs' / 'output'}\nseed: 0\n"
    )
    return params


def disk_mib(*folders: Path) -> float:
    files = (p for folder in folders for p in folder.rglob("*") if p.is_file())
    return round(
        sum(p.stat().st_size for p in files) / 2**20, 2
    )  # two decimals: a few dozen pairs store some kilobytes


def run_once(
    command: list[str], log: Path, cache: Path, stop_at: tuple[Path, int] | None = None
) -> tuple[int, float, int, int]:
    """Exit code, wall seconds, peak resident MiB of the process tree and of its largest process; with ``stop_at`` (the
    folder of the run's match stores, a pair count) SIGKILL its process group once a store holds that many pairs."""
    from gvbench_nb.runner.store import ShardedStore

    start, peak, largest = time.perf_counter(), 0, 0
    with open(log, "a") as handle:
        env = {**os.environ, "GVBENCH_CACHE": str(cache)}  # a cache of the run's own, empty at its start
        process = subprocess.Popen(
            command, stdout=handle, stderr=subprocess.STDOUT, cwd=REPO, env=env, start_new_session=True
        )
    root = psutil.Process(process.pid)
    while process.poll() is None:
        try:
            tree = [root, *root.children(recursive=True)]
            rss = [p.memory_info().rss for p in tree if p.is_running()]
            peak, largest = max(peak, sum(rss)), max(largest, *rss)
        except psutil.Error:
            pass  # a process ended between the listing and the read
        if stop_at and any(len(ShardedStore(store)) >= stop_at[1] for store in stop_at[0].glob("*")):
            os.killpg(process.pid, signal.SIGKILL)
            process.wait()
            break
        time.sleep(0.2)
    return process.returncode, time.perf_counter() - start, peak >> 20, largest >> 20


def measure(params: Path, method: str, folder: Path, stop_at: int | None = None) -> dict[str, object]:
    """One run of ``method`` on ``params`` into ``folder`` (emptied first unless resuming)."""
    command = [sys.executable, "-m", "gvbench_nb", "run", str(params), "--methods", method]
    command += ["--output-dir", str(folder / "output")]
    code, wall, peak, largest = run_once(
        command, folder / "run.log", folder / "cache", (folder / "cache" / "matches", stop_at) if stop_at else None
    )
    if stop_at is None and code != 0:
        raise SystemExit(f"error: the run of {method} exited with {code}; its log is {folder / 'run.log'}")
    n_pairs = len(pd.read_csv(method_outputs.method_dir(folder / "output", method) / "pairs.csv")) if code == 0 else 0
    return {
        "exit_code": code,
        "method": method,
        "n_pairs": n_pairs,
        "wall_seconds": round(wall, 1),
        "seconds_per_pair": round(wall / max(n_pairs, 1), 5),
        "peak_rss_mib": peak,
        "largest_process_peak_rss_mib": largest,
        "cache_mib": disk_mib(folder / "cache"),
        "store_mib": disk_mib(*(folder / "cache" / "matches").glob(f"{method}-*")),
        "load_average": round(os.getloadavg()[0], 2),
    }


def same_without_timers(a: Path, b: Path) -> bool:
    """Equal tables, timers aside (seconds, which run timed them, when it finished)."""
    left, right = (pd.read_csv(p).filter(regex=r"^(?!.*seconds|timers$|finished_at$)") for p in (a, b))
    return left.equals(right)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sizes", default="2000,8000,34400", help="comma-separated pair counts")
    parser.add_argument("--methods", default="orb-nn,sift-nn")
    parser.add_argument("--frames", type=int, help="only the first N frames of each traversal (default all 200)")
    parser.add_argument("--kill-at", type=float, help="kill and resume the largest size's first method at this share")
    parser.add_argument("--out", default=str(REPO / "outputs" / "official_size"), help="folder for everything")
    args = parser.parse_args(argv)
    root, out = fetch.data_dir() / "gardens_point", Path(args.out).resolve()
    if not all((root / folder).is_dir() for folder in (*QUERY_FOLDERS, REFERENCE_FOLDER)):
        raise SystemExit(f"error: Gardens Point is not in {root}: run `python -m gvbench_nb data fetch gardens_point`")
    if args.kill_at is not None and not 0 < args.kill_at < 1:
        raise SystemExit(f"error: --kill-at must lie between 0 and 1, got {args.kill_at}")
    sizes, methods = [int(n) for n in args.sizes.split(",")], args.methods.split(",")
    params = {n: write_sequence(out, root, n, args.frames) for n in sizes}
    rows = []
    for n in sizes:
        for method in methods:
            shutil.rmtree(out / "runs" / f"{n}_{method}", ignore_errors=True)
            (out / "runs" / f"{n}_{method}").mkdir(parents=True)
            rows.append(measure(params[n], method, out / "runs" / f"{n}_{method}"))
            print(pd.DataFrame(rows[-1:]).to_string(index=False), flush=True)
    table = bench.merge_csv(out / "official_size.csv", pd.DataFrame(rows), KEYS).sort_values(KEYS)
    print(table.to_string(index=False))
    largest = table.sort_values("n_pairs").groupby("method").tail(1).set_index("method")["seconds_per_pair"]
    official = int(estimate.official_sequence_sizes(fetch.data_dir() / "gvbench_gt")["n_pairs"].sum())
    for method, seconds in largest.items():
        print(f"{method}: the six official sequences ({official} pairs) in {official * seconds / 3600:.1f} h here")
    if args.kill_at is not None:
        n, method = max(sizes), methods[0]
        folder, done = out / "runs" / f"{n}_{method}_killed", out / "runs" / f"{n}_{method}" / "output"
        shutil.rmtree(folder, ignore_errors=True)
        folder.mkdir(parents=True)
        killed = measure(params[n], method, folder, stop_at=round(args.kill_at * n))
        resumed = measure(params[n], method, folder)
        tables = [
            (method_outputs.method_dir(f, method) / "pairs.csv", f / "results.csv") for f in (done, folder / "output")
        ]
        equal = all(same_without_timers(a, b) for a, b in zip(*tables))
        print(
            f"kill -9 after {killed['wall_seconds']} s (exit {killed['exit_code']}, {args.kill_at:g} of {n} pairs "
            f"in the store), resumed in "
            f"{resumed['wall_seconds']} s: per-pair table and results "
            f"{'EQUAL' if equal else 'DIFFER from'} the uninterrupted run's (timers aside)"
        )
        if not equal:
            return 1
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
