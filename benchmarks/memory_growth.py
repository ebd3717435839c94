"""Where a run's peak memory grows with the pairs: the peak resident memory of one method's
extraction, matching and pairs table (``run_method``, as ``run`` calls it, no notebooks) on
the first N pairs, with the recent-features cache at its default bound and at a smaller one.
Each measurement is its own process (a fresh peak), in fresh output and cache folders.

    python benchmarks/memory_growth.py params/gardens_point.yaml --method sift-nn --pairs 500,2000 --feature-cache-mib 256,16
"""

from __future__ import annotations

import argparse
import resource
import subprocess
import sys
import tempfile
from pathlib import Path


def measure(params_file: str, method: str, pairs: int, cache_mib: int) -> int:
    """This process's peak resident memory in MiB after the method's work on ``pairs`` pairs."""
    from gvbench_nb.runner import config, method_runs, pair_matching, sequence_build

    bounded = pair_matching.FeatureCache.__init__

    def init(self: pair_matching.FeatureCache, read: object, max_bytes: int = 0) -> None:
        bounded(self, read, cache_mib << 20)  # type: ignore[arg-type]

    pair_matching.FeatureCache.__init__ = init  # type: ignore[method-assign]
    with tempfile.TemporaryDirectory() as folder:
        params = config.load_params(
            params_file, limit=pairs, output_dir=str(Path(folder) / "out"), cache_dir=str(Path(folder) / "cache")
        )
        sequence = sequence_build.prepare_sequence(params)
        method_runs.run_method_of_params(params, sequence, method, progress=False)
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss // 1024


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("params", help="params YAML, e.g. params/gardens_point.yaml")
    parser.add_argument("--method", default="sift-nn")
    parser.add_argument("--pairs", default="500,2000", help="comma-separated pair counts (the first N pairs)")
    parser.add_argument("--feature-cache-mib", default="256,16", help="comma-separated bounds of the features cache")
    parser.add_argument("--measure", nargs=2, type=int, metavar=("PAIRS", "MIB"), help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.measure:
        print(measure(args.params, args.method, *args.measure))
        return 0
    print("pairs  feature_cache_mib  peak_mib")
    for cache_mib in (int(m) for m in args.feature_cache_mib.split(",")):
        for pairs in (int(n) for n in args.pairs.split(",")):
            command = [
                sys.executable,
                __file__,
                args.params,
                "--method",
                args.method,
                "--measure",
                str(pairs),
                str(cache_mib),
            ]
            peak = subprocess.run(command, check=True, capture_output=True, text=True).stdout.split()[-1]
            print(f"{pairs:5d}  {cache_mib:17d}  {peak:>8}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
