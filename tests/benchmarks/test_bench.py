"""The bench: both pipelines agree on scores, mismatches fail loudly, summaries and estimates add up."""

from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import speed as speed_cli
import speed_bench as bench
import speed_estimate as estimate
import torch
from written_runs import add_run

from gvbench_nb import methods
from gvbench_nb.data.sequences import Pair, Sequence


def gardens_point_pairs(shared_data: Path, night: bool) -> Sequence:
    """Five pairs: two queries, each with a true and a false reference, plus one reused reference. Night
    queries against day references, or day against day (COLMAP SIFT finds too few night-to-day matches for
    scores to vary)."""
    query, frames = ("night_right", (60, 60, 140, 140, 61)) if night else ("day_right", (60, 60, 140, 140, 62))
    references = (60, 140, 141, 60, 60) if night else (61, 140, 141, 62, 61)
    pairs = [
        Pair(f"{query}/Image{q:03d}.jpg", f"day_right/Image{r:03d}.jpg", label)
        for q, r, label in zip(frames, references, (1, 0, 1, 0, 1))
    ]
    return Sequence("gp_bench" if night else "gp_bench_day", shared_data / "gardens_point", pairs)


@pytest.mark.slow
@pytest.mark.real_data
@pytest.mark.parametrize("method", ["sift-nn", "disk-lg"])  # disk-lg: ours prepares LightGlue once per image
def test_per_pair_pipeline_and_ours_give_identical_scores(shared_data, tmp_path, method):
    sequence = gardens_point_pairs(shared_data, night=method != "sift-nn")
    conf = methods.resolve_method(method, "repository")
    if method == "disk-lg":  # half the keypoints, a quarter of LightGlue's attention, DISK on a quarter of
        # the pixels (512 on the long side, not 1024): the same comparison
        conf["extractor"]["max_keypoints"] = 1024
        conf["extractor"]["model_input_long_side"] = 512
    ours, our_seconds = bench.run_cached_pipeline(sequence, conf, tmp_path, torch.device("cpu"), seed=3)
    reference, reference_seconds = bench.run_per_pair_pipeline(sequence, conf, torch.device("cpu"), seed=3)
    bench.check_same_scores(ours, reference, "test")  # raises on any difference
    assert ours["num_inliers"].tolist() == reference["num_inliers"].tolist()
    true_pairs = np.array([pair.label == 1 for pair in sequence.pairs])
    assert (ours["num_matches"][true_pairs] > 0).all() and ours["num_inliers"].nunique() > 1  # not trivially equal
    for seconds in (our_seconds, reference_seconds):
        assert seconds["wall"] == pytest.approx(seconds["extract"] + seconds["match_verify_wall"] + seconds["other"])
        assert min(seconds[s] for s in ("extract", "match", "verify")) > 0


@pytest.mark.real_data
def test_the_bench_runs_ours_with_two_workers_and_the_reference_with_one(shared_data):
    rows = bench.bench_method(
        gardens_point_pairs(shared_data, night=True), "sift-nn", "repository", repeats=1, device="cpu", progress=False
    )
    assert dict(zip(rows["pipeline"], rows["workers"])) == {bench.CACHED: 2, bench.PER_PAIR: 1}
    summary = bench.summarize_bench(rows).iloc[0]
    assert summary["cached_workers"] == 2 and summary["scores_identical"]
    # the per-pair pipeline's own split bounds what caching alone can gain
    per_pair = rows.set_index("pipeline").loc[bench.PER_PAIR]
    expected = 1 / (per_pair["pairs_per_second"] * per_pair["match_verify_wall_seconds_per_pair"])
    assert summary["speedup_if_extraction_were_free"] == pytest.approx(expected) and expected > 1


def test_a_score_mismatch_fails_loudly_naming_the_pair():
    ours = pd.DataFrame(
        {"query": ["q0", "q1"], "reference": ["r0", "r1"], "num_matches": [50, 40], "num_inliers": [30, 12]}
    )
    other = ours.copy()
    bench.check_same_scores(ours, other, "same")
    other.loc[1, "num_inliers"] = 13
    with pytest.raises(bench.ScoreMismatchError, match=r"(?s)1 of 2 pairs.*pair 1: q1 r1: cached 12 inliers"):
        bench.check_same_scores(ours, other, "where")


def timing_rows(cached_rates, per_pair_rates) -> pd.DataFrame:
    run = {"sequence": "s", "method": "sift-nn", "profile": "repository", "n_pairs": 100, "n_images": 40}
    machine = {"device": "cpu", "device_name": "x86_64", "torch_threads": 1, "opencv_threads": 1, "cpu_count": 2}
    rows = []
    for repeat, (fast, slow) in enumerate(zip(cached_rates, per_pair_rates)):
        for which, rate in ((bench.CACHED, fast), (bench.PER_PAIR, slow)):
            timed = {"repeat": repeat, "pipeline": which, "wall_seconds": 100 / rate, "pairs_per_second": rate}
            for stage, share in (("extract", 0.5), ("match", 0.3), ("verify", 0.2), ("other", 0.0)):
                timed[f"{stage}_seconds_per_pair"] = share / rate
            # ours overlaps matching with verification: less wall time than their sum
            timed["match_verify_wall_seconds_per_pair"] = (0.35 if which == bench.CACHED else 0.5) / rate
            load = {"loadavg_1m": 1.0 + repeat, "loadavg_5m": 1.0, "date": "2026-01-01"}
            rows.append(run | timed | machine | load)
    return pd.DataFrame(rows)


def test_summary_takes_the_median_of_per_repeat_ratios():
    summary = bench.summarize_bench(timing_rows([10.0, 30.0, 12.0], [2.0, 3.0, 4.0])).iloc[0]
    assert summary["speedup"] == pytest.approx(5.0)  # ratios 5, 10, 3
    assert (summary["speedup_min"], summary["speedup_max"]) == pytest.approx((3.0, 10.0))
    assert summary["cached_pairs_per_second"] == 12.0 and summary["per_pair_pairs_per_second"] == 3.0
    assert summary["meets_target"] and summary["speedup_target"] == 5.0
    # the per-pair pipeline spends half its time matching and verifying: caching gains at most 2x
    assert summary["speedup_if_extraction_were_free"] == pytest.approx(2.0)
    slower = bench.summarize_bench(timing_rows([8.0], [2.0])).iloc[0]
    assert not slower["meets_target"]
    assert summary["uses_per_image"] == 5.0
    assert summary["cached_extract_seconds_per_image"] == pytest.approx(0.5 / 12 * 100 / 40)
    assert (summary["loadavg_1m_start"], summary["loadavg_1m_max"]) == (1.0, 3.0)


def test_bench_csvs_keep_other_runs_and_replace_the_same_run(tmp_path):
    path = tmp_path / "summary.csv"
    keys = ["sequence", "method", "profile", "n_pairs"]
    first = bench.summarize_bench(timing_rows([10.0], [2.0]))
    bench.merge_csv(path, first, keys)
    paper = first.assign(profile="paper")
    bench.merge_csv(path, paper, keys)
    again = bench.merge_csv(path, first.assign(speedup=7.0), keys)
    assert sorted(again["profile"]) == ["paper", "repository"]
    assert again.set_index("profile").loc["repository", "speedup"] == 7.0


def test_estimate_scales_measured_costs_by_images_and_pairs():
    summary = bench.summarize_bench(timing_rows([10.0], [2.0]))
    sizes = pd.DataFrame([{"sequence": "day", "n_pairs": 3600, "n_images": 720, "uses_per_image": 10.0}])
    row = estimate.estimate_official_runtime(estimate.costs_from_bench(summary), sizes).iloc[0]
    per_image = 0.5 / 10 * 100 / 40
    assert row["cached_hours"] == pytest.approx((720 * per_image + 3600 * 0.35 / 10) / 3600)  # the wall, not the sum
    assert row["per_pair_hours"] == pytest.approx(3600 / 2.0 / 3600)


def test_estimate_from_runs_costs_every_method_from_its_per_pair_timers(tmp_path):

    # Two queries x two references; each image extracted once in 0.4 s, its time shared by its 2 pairs.
    table = pd.DataFrame(
        {
            "query": ["q0", "q0", "q1", "q1"],
            "reference": ["r0", "r1", "r0", "r1"],
            "label": [1, 0, 0, 1],
            "profile": "repository",
            "extract_seconds": 0.4,
            "match_seconds": [0.1, 0.2, 0.3, 0.2],
            "verify_seconds": 0.05,
        }
    )
    for method in ("xfeat-nn", "sift-nn"):
        run = {"environment": {"device_name": "cpu-x"}, "finished_at": "2026-11-22T00:00:00+00:00"}
        add_run(tmp_path, method, table, run)
    costs = estimate.costs_from_runs(tmp_path).set_index("method")
    assert list(costs.index) == ["sift-nn", "xfeat-nn"]  # registry order
    assert costs.loc["sift-nn", "extract_seconds_per_image"] == pytest.approx(4 * 0.4 / 4)
    assert costs.loc["sift-nn", "cached_seconds_per_pair"] == pytest.approx(0.2 + 0.05)
    assert costs.loc["sift-nn", "per_pair_seconds_per_pair"] == pytest.approx(2 * 0.4 + 0.25)
    sizes = pd.DataFrame([{"sequence": "day", "n_pairs": 3600, "n_images": 720, "uses_per_image": 10.0}])
    row = estimate.estimate_official_runtime(costs.reset_index(), sizes).iloc[0]
    assert row["source"] == "run" and row["cached_hours"] == pytest.approx((720 * 0.4 + 3600 * 0.25) / 3600)


@pytest.mark.slow
@pytest.mark.real_data
def test_official_sizes_count_unique_images(shared_data):
    sizes = estimate.official_sequence_sizes(shared_data / "gvbench_gt").set_index("sequence")
    assert list(sizes.index) == list(bench.OFFICIAL_SEQUENCES)
    assert sizes.loc["uacampus", "n_pairs"] == sum(
        1 for line in (shared_data / "gvbench_gt" / "uacampus.txt").read_text().splitlines() if line.strip()
    )
    assert (sizes["n_images"] < sizes["n_pairs"]).all()


@pytest.mark.real_data
def test_scaling_table_sums_the_measured_stage_costs(shared_data):
    sequence = gardens_point_pairs(shared_data, night=True)
    table = bench.scaling_table(sequence, "sift-nn", "repository", limits=(2, 5, 50), device="cpu").set_index("n_pairs")
    assert list(table.index) == [2, 5]  # 50 is capped at the sequence's length
    assert table.loc[5, "n_images"] == len(sequence.images) == 6
    assert table.loc[2, "n_images"] == 3
    assert table.loc[5, "extract_seconds"] > table.loc[2, "extract_seconds"] > 0
    # The per-pair pipeline extracts each pair's two images: 10 extractions for 6 images here.
    assert table.loc[5, "per_pair_extract_seconds"] > table.loc[5, "extract_seconds"]
    assert np.isclose(
        table.loc[5, "total_seconds"], table.loc[5, ["extract_seconds", "match_seconds", "verify_seconds"]].sum()
    )


def test_the_bench_parser_reads_its_options():
    argv = ["p.yaml", "--methods", "sift-nn,disk-lg", "--limit", "50", "--repeats", "2", "--profile", "repository"]
    args = speed_cli.build_parser().parse_args(argv)
    expected = ("p.yaml", "sift-nn,disk-lg", 50, 2, "repository")
    assert (args.params, args.methods, args.limit, args.repeats, args.profile) == expected
    assert args.handler is speed_cli.command_bench


def test_bench_takes_jobs_and_estimate_names_the_lists_before_any_timing(tmp_path, monkeypatch, capsys):
    assert speed_cli.build_parser().parse_args(["p.yaml"]).jobs == 2  # the bench's own default
    assert speed_cli.build_parser().parse_args(["p.yaml", "--jobs", "1"]).jobs == 1
    monkeypatch.setenv("GVBENCH_DATA", str(tmp_path))
    timed = []
    monkeypatch.setattr(bench, "bench_method", lambda *args, **kwargs: timed.append(args))
    for argv in (["--estimate"], ["params/sample.yaml", "--estimate"]):
        assert speed_cli.main(argv) == 2
        error = capsys.readouterr().err.strip()
        assert error == (
            "error: bench --estimate needs the official pair lists, and day.txt, night.txt, nordland.txt, "
            f"season.txt, uacampus.txt, weather.txt are missing from {tmp_path / 'gvbench_gt'}: run "
            "`python -m gvbench_nb data fetch gvbench-lists` (or set GVBENCH_DATA to the folder holding gvbench_gt/)"
        )
    assert timed == []
