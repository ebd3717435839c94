"""Beyond the paper: AP and MR of the protocol's score (``num_inliers``) beside those of a score that
counts distinct keypoints, min(distinct query, distinct reference keypoints among the inliers), read
from finished runs' pairs.csv (nothing recomputed), with 95 % bootstrap intervals over queries (the
same resamples for both scores of a method). Also counts the pairs whose inliers collapse
(docs/protocol.md, "Collapsed inliers").

    python benchmarks/distinct_keypoints.py outputs/gp_repository outputs/gp_paper --methods sift-nn,orb-nn,xfeat-nn
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import pandas as pd

from gvbench_nb.evaluation import bootstrap, collapsed_inliers
from gvbench_nb.reporting.tables import markdown_table
from gvbench_nb.runner import method_outputs, scoring

DISTINCT = "distinct"  # the suffix of a method's distinct-keypoint score in the bootstrap


def with_interval(row: pd.Series, metric: str) -> str:
    return f"{row[metric]:.3f} [{row[f'{metric}_low']:.3f}, {row[f'{metric}_high']:.3f}]"


def method_rows(folder: Path, method: str, resamples: int, seed: int) -> dict[str, object]:
    """One row: the protocol's and the distinct-keypoint score's AP and MR with intervals, collapsed pairs."""
    table = scoring.load_pairs_table(folder, method)
    distinct = collapsed_inliers.distinct_inlier_keypoints(table)
    if distinct.isna().any():
        raise SystemExit(
            f"{folder / method / 'pairs.csv'} does not count the distinct keypoints among the inliers; run the "
            f"method again (python -m gvbench_nb run PARAMS --methods {method} --output-dir {folder})"
        )
    boot = bootstrap.bootstrap({method: table, DISTINCT: table.assign(score=distinct)}, resamples, seed)
    intervals = bootstrap.intervals_of(boot).set_index("method")
    protocol, counted = intervals.loc[method], intervals.loc[DISTINCT]
    collapsed = collapsed_inliers.collapsed(table)
    profile = method_outputs.read_run_json(folder, method)["conf"]["profile"]
    return {
        "method": method,
        "profile": profile,
        "AP num_inliers": with_interval(protocol, "ap"),
        "MR num_inliers": with_interval(protocol, "max_recall"),
        "AP distinct keypoints": with_interval(counted, "ap"),
        "MR distinct keypoints": with_interval(counted, "max_recall"),
        "collapsed false / true pairs": f"{int((collapsed & (table['label'] == 0)).sum())} / "
        f"{int((collapsed & (table['label'] == 1)).sum())}",
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("output_dirs", nargs="+", help="output folders of finished runs")
    parser.add_argument("--methods", help="comma-separated methods (default: every finished one)")
    parser.add_argument("--resamples", type=int, default=bootstrap.DEFAULT_RESAMPLES, help="query resamples")
    parser.add_argument("--seed", type=int, default=0, help="seed of the query draws")
    args = parser.parse_args(argv)
    wanted = [m.strip() for m in args.methods.split(",")] if args.methods else None
    rows = []
    for folder in map(Path, args.output_dirs):
        for method in scoring.readable_methods(folder, wanted):
            rows.append(method_rows(folder, method, args.resamples, args.seed))
    print(markdown_table(pd.DataFrame(rows)))
    print(
        f"\n[95 % bootstrap intervals over queries, {args.resamples} resamples, seed {args.seed}]; distinct keypoints: "
        "min(distinct query, distinct reference keypoints among the inliers); collapsed: "
        f"{collapsed_inliers.RULE}"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
