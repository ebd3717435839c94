"""What a run of the official sequences would cost on this machine, estimated from the bench's
summary or from a finished run's per-image and per-pair timers (``--estimate``).
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import pandas as pd
import speed_bench as bench
from speed_bench import CACHED

from gvbench_nb.data.sequences import read_pairs
from gvbench_nb.io_utils import atomic_write_csv
from gvbench_nb.runner import run_estimate, scoring

if TYPE_CHECKING:
    pass


# ------------------------------------------------------------------- estimates --
def require_official_lists(gt_dir: Path) -> None:
    """The estimate counts the official sequences' pairs: their lists must be in ``gt_dir``."""
    from gvbench_nb.data.fetch import DataError

    missing = [name for name in bench.OFFICIAL_SEQUENCES if not (Path(gt_dir) / f"{name}.txt").is_file()]
    if missing:
        raise DataError(
            f"bench --estimate needs the official pair lists, and {', '.join(f'{m}.txt' for m in missing)} "
            f"{'is' if len(missing) == 1 else 'are'} missing from {gt_dir}: run `python -m gvbench_nb data fetch gvbench-lists` "
            "(or set GVBENCH_DATA to the folder holding gvbench_gt/)"
        )


def official_sequence_sizes(gt_dir: Path) -> pd.DataFrame:
    """Pairs and unique images of each official sequence, counted from its pair list."""
    require_official_lists(gt_dir)
    rows = []
    for name in bench.OFFICIAL_SEQUENCES:
        pairs = read_pairs(Path(gt_dir) / f"{name}.txt")
        images = {p for pair in pairs for p in (pair.query, pair.reference)}
        rows.append(
            {
                "sequence": name,
                "n_pairs": len(pairs),
                "n_images": len(images),
                "uses_per_image": 2 * len(pairs) / len(images),
            }
        )
    return pd.DataFrame(rows)


def costs_from_bench(summary: pd.DataFrame) -> pd.DataFrame:
    """Per (method, profile): measured seconds per unique image (extraction) and per pair
    (ours: matching and verification, overlapped, plus overhead; the per-pair pipeline:
    everything). From the largest bench run of each."""
    latest = summary.sort_values("n_pairs").groupby(["method", "profile"], sort=False).tail(1)
    rows = []
    for _, measured in latest.iterrows():
        # Summaries written before matching overlapped verification have no wall column.
        wall_column = f"{CACHED}_match_verify_wall_seconds_per_pair"
        stages = ("match_verify_wall", "other") if pd.notna(measured.get(wall_column)) else ("match", "verify", "other")
        rows.append(
            {
                "method": measured["method"],
                "profile": measured["profile"],
                "source": "bench",
                "extract_seconds_per_image": measured["cached_extract_seconds_per_image"],
                "cached_seconds_per_pair": sum(measured[f"{CACHED}_{s}_seconds_per_pair"] for s in stages),
                "per_pair_seconds_per_pair": 1.0 / measured["per_pair_pairs_per_second"],
                "measured_on": f"bench: {measured['sequence']} ({measured['n_pairs']} pairs), {measured['device_name']}, "
                f"{measured['cpu_count']} CPUs, load {measured['loadavg_1m_start']}",
            }
        )
    return pd.DataFrame(rows)


def costs_from_runs(output_dir: Path) -> pd.DataFrame:
    """The same costs from the per-pair timers of finished runs (``<output_dir>/<method>/pairs.csv``),
    for every method that ran. The per-pair pipeline is then estimated as two extractions
    and one match a pair (without decoding, which the bench measures)."""
    from gvbench_nb.evaluation.run_tables import load_run

    rows = []
    for method in scoring.readable_methods(output_dir):  # what `results` refuses, the estimate refuses
        table = scoring.load_pairs_table(output_dir, method)
        n_images = len(set(table["query"]) | set(table["reference"]))
        # A pair's extract_seconds is its images' times shared among their pairs: the sum is the total.
        per_image = float(table["extract_seconds"].sum()) / n_images
        per_pair = float((table["match_seconds"] + table["verify_seconds"]).mean())
        run = load_run(output_dir, method)
        rows.append(
            {
                "method": method,
                "profile": table["profile"].iat[0],
                "source": "run",
                "extract_seconds_per_image": per_image,
                "cached_seconds_per_pair": per_pair,
                "per_pair_seconds_per_pair": 2 * per_image + per_pair,
                "measured_on": f"run: {Path(output_dir).name} ({len(table)} pairs), "
                f"{run['environment']['device_name']}, finished {run['finished_at']}",
            }
        )
    return pd.DataFrame(rows)


def estimate_official_runtime(costs: pd.DataFrame, sizes: pd.DataFrame) -> pd.DataFrame:
    """Hours of each official sequence x costed (method, profile), both pipelines.

    Ours: ``run_estimate.run_seconds``, the model a run's own estimate uses. The per-pair
    pipeline: pairs x its seconds per pair.
    """
    rows = []
    for _, cost in costs.iterrows():
        for _, size in sizes.iterrows():
            cached_seconds = run_estimate.run_seconds(
                size["n_images"], cost["extract_seconds_per_image"], size["n_pairs"], cost["cached_seconds_per_pair"]
            )
            reference_seconds = size["n_pairs"] * cost["per_pair_seconds_per_pair"]
            rows.append(
                {
                    "sequence": size["sequence"],
                    "method": cost["method"],
                    "profile": cost["profile"],
                    "source": cost["source"],
                    "n_pairs": size["n_pairs"],
                    "n_images": size["n_images"],
                    "cached_hours": cached_seconds / 3600,
                    "per_pair_hours": reference_seconds / 3600,
                    "speedup": reference_seconds / cached_seconds,
                    "measured_on": cost["measured_on"],
                }
            )
    return pd.DataFrame(rows)


def print_estimate(
    bench_dir: Path = bench.DEFAULT_BENCH_DIR, gt_dir: Path | None = None, runs: Path | None = None
) -> pd.DataFrame:
    """Print (and write ``estimate.csv``) the official-sequence estimate from ``summary.csv``
    and, with ``runs`` (a sequence output folder), from every method that ran there."""
    from gvbench_nb.runner.config import data_dir

    summary_path = Path(bench_dir) / "summary.csv"
    if not summary_path.is_file() and runs is None:
        raise FileNotFoundError(
            f"no bench summary at {summary_path}: run `python benchmarks/speed.py PARAMS` "
            "first, or give --runs outputs/<sequence>"
        )
    if gt_dir is None:
        gt_dir = data_dir() / "gvbench_gt"
    sizes = official_sequence_sizes(gt_dir)
    costs = [costs_from_bench(pd.read_csv(summary_path, keep_default_na=False))] if summary_path.is_file() else []
    if runs is not None:
        costs.append(costs_from_runs(Path(runs)))
    estimate = estimate_official_runtime(pd.concat(costs, ignore_index=True), sizes)
    atomic_write_csv(Path(bench_dir) / "estimate.csv", estimate)
    print("Official sequences (from their pair lists):")
    print(sizes.to_string(index=False, float_format=lambda v: f"{v:.2f}"))
    totals = estimate.groupby(["source", "method", "profile"], sort=False)[["cached_hours", "per_pair_hours"]].sum()
    print("\nEstimated hours on this CPU (extraction cost per image and matching cost per pair as measured):")
    print(estimate.drop(columns="measured_on").to_string(index=False, float_format=lambda v: f"{v:.2f}"))
    print("\nAll six sequences, per method:")
    print(totals.to_string(float_format=lambda v: f"{v:.2f}"))
    print(
        "\nCaveats: measured on Gardens Point (960x540 images); the official images differ in size "
        "(extraction scales roughly with pixels, matching with keypoints), and the machine was shared "
        "(load averages in summary.csv). Treat these as order-of-magnitude figures."
    )
    print(bench.GPU_NOTE)
    return estimate
