"""Sharded runs (by hand and through Dask) merge into exactly the unsharded result; how many jobs
a run does at once, and on how many threads each."""

import os
from pathlib import Path

import cv2
import pandas as pd
import pytest
import torch
import yaml

from gvbench_nb import methods
from gvbench_nb.data.sequences import Pair, Sequence, write_pairs
from gvbench_nb.runner import concurrency, config, distributed, image_features, method_runs, scoring, sequence_build

METHOD, PROFILE = "sift-nn", "repository"


def twelve_pairs() -> list[Pair]:
    """Three day queries, each with two true neighbouring frames and two false ones (12 pairs).
    Day frames: COLMAP SIFT finds hardly any night-to-day matches at 512 px, so no inliers."""
    return [
        Pair(f"day_right/Image{q:03d}.jpg", f"day_right/Image{r:03d}.jpg", label)
        for q in (30, 90, 150)
        for r, label in ((q + 1, 1), (q + 2, 1), ((q + 50) % 200, 0), ((q + 100) % 200, 0))
    ]


def make_params(shared_data: Path, folder: Path) -> dict:
    """A params file of its own (own output and cache folders) over the same pair file."""
    folder.mkdir(parents=True, exist_ok=True)
    pairs = folder.parent / "pairs.txt"
    if not pairs.is_file():
        write_pairs(pairs, twelve_pairs())
    params = {"sequence": "gp_shards", "pairs": str(pairs), "image_root": str(shared_data / "gardens_point")}
    params |= {"methods": [METHOD], "profile": PROFILE, "output_dir": str(folder / "out")}
    (folder / "params.yaml").write_text(yaml.safe_dump(params | {"cache_dir": str(folder / "cache")}))
    return config.load_params(folder / "params.yaml")


def without_timings(table: pd.DataFrame) -> pd.DataFrame:
    return table[[c for c in table.columns if not c.endswith("_seconds")]]


@pytest.fixture(scope="module")
def unsharded(shared_data, tmp_path_factory) -> pd.DataFrame:
    params = make_params(shared_data, tmp_path_factory.mktemp("runs") / "unsharded")
    method_runs.run_method_of_params(params, sequence_build.prepare_sequence(params), METHOD, progress=False)
    return scoring.load_pairs_table(Path(params["output_dir"]), METHOD)


@pytest.mark.slow
@pytest.mark.real_data
def test_shards_run_by_hand_then_merged_equal_the_unsharded_run(shared_data, unsharded, tmp_path):
    params = make_params(shared_data, tmp_path / "sharded")
    for index in (2, 0, 1):  # any order
        distributed.run_shard(params, index, 3, threads=1, progress=False)
    results = distributed.merge_runs(params)
    merged = scoring.load_pairs_table(Path(params["output_dir"]), METHOD)
    assert len(merged) == 12 and merged["num_inliers"].max() > 0
    pd.testing.assert_frame_equal(without_timings(merged), without_timings(unsharded))
    assert results["n_pairs"].tolist() == [12]
    run = pd.read_json(Path(params["output_dir"]) / METHOD / "run.json", typ="series")
    assert run["n_pairs"] == 12 and run["this_run"]["sharded"]


@pytest.mark.slow
@pytest.mark.real_data
def test_dask_local_cluster_run_equals_the_unsharded_run(shared_data, unsharded, tmp_path):
    params = make_params(shared_data, tmp_path / "dask")
    results = distributed.run_sharded(params, n_shards=3, n_workers=2, processes=False, threads=1, progress=False)
    merged = scoring.load_pairs_table(Path(params["output_dir"]), METHOD)
    pd.testing.assert_frame_equal(without_timings(merged), without_timings(unsharded))
    assert results.set_index("method").loc[METHOD, "ap"] == pytest.approx(
        scoring.evaluate(Path(params["output_dir"]), [METHOD], write=False)["ap"].iat[0]
    )
    run = pd.read_json(Path(params["output_dir"]) / METHOD / "run.json", typ="series")
    assert [s["shard"] for s in run["this_run"]["shards"]] == ["0/3", "1/3", "2/3"]
    # Every image was extracted exactly once across the extraction shards.
    store = image_features.feature_store(
        Path(params["cache_dir"]), methods.resolve_method(METHOD, PROFILE)["extractor"]
    )
    assert len(store) == len(sequence_build.prepare_sequence(params).images)


@pytest.mark.real_data
def test_merge_with_a_missing_shard_names_the_missing_pairs(shared_data, tmp_path):
    params = make_params(shared_data, tmp_path / "partial")
    distributed.run_shard(params, 0, 3, threads=1, progress=False)
    with pytest.raises(distributed.ShardError, match=r"8 of 12 pairs have no result.*first: pair 1, "):
        distributed.merge_runs(params)
    assert not (Path(params["output_dir"]) / METHOD / "pairs.csv").exists()


def test_pair_shards_partition_the_pairs():
    sequence = Sequence("s", Path("/images"), twelve_pairs())
    shards = [distributed.pair_shard(sequence, i, 5) for i in range(5)]
    assert sorted((p for s in shards for p in s.pairs), key=sequence.pairs.index) == sequence.pairs


@pytest.mark.parametrize("text", ["3/3", "-1/2", "1", "a/b", "0/0"])
def test_parse_shard_reads_index_and_count_and_rejects_bad_values(text):
    assert distributed.parse_shard("2/5") == (2, 5)
    with pytest.raises(ValueError, match="shard"):
        distributed.parse_shard(text)


def test_job_count_comes_from_the_argument_then_gvbench_jobs(monkeypatch):
    monkeypatch.delenv("GVBENCH_JOBS", raising=False)
    assert concurrency.job_count() == concurrency.available_cores() == len(os.sched_getaffinity(0))
    monkeypatch.setenv("GVBENCH_JOBS", "3")
    assert concurrency.job_count() == 3 and concurrency.job_count(2) == 2
    with pytest.raises(ValueError, match=r"--jobs or \$GVBENCH_JOBS"):
        concurrency.job_count(0)
    monkeypatch.setenv("GVBENCH_JOBS", "two")
    with pytest.raises(ValueError, match=r"got 'two' \(--jobs or \$GVBENCH_JOBS\)"):
        concurrency.job_count()


def test_threads_a_job_share_the_cores_between_the_jobs_in_torch_opencv_and_blas(monkeypatch):
    from threadpoolctl import threadpool_info

    monkeypatch.delenv("GVBENCH_THREADS", raising=False)
    monkeypatch.setattr(concurrency, "available_cores", lambda: 4)
    before = torch.get_num_threads(), cv2.getNumThreads()
    try:
        assert concurrency.configure_threads(jobs=2) == 2
        assert torch.get_num_threads() == cv2.getNumThreads() == 2
        assert {pool["num_threads"] for pool in threadpool_info() if pool["user_api"] == "blas"} <= {2}
        assert concurrency.configure_threads(jobs=8) == 1  # never fewer than one a job
        assert concurrency.configure_threads(3, jobs=2) == 3  # asked for
        monkeypatch.setenv("GVBENCH_THREADS", "2")
        assert concurrency.configure_threads(jobs=4) == 2
    finally:
        concurrency.configure_threads(before[0])
        cv2.setNumThreads(before[1])


def test_run_jobs_flag_is_exported_for_the_notebook_kernels_and_checked_like_the_variable(monkeypatch, capsys):
    from gvbench_nb import cli

    monkeypatch.delenv("GVBENCH_JOBS", raising=False)
    args = cli.build_parser().parse_args(["run", "p.yaml", "--jobs", "2", "--dask-workers", "3"])
    assert args.jobs == 2 and os.environ["GVBENCH_JOBS"] == "2" and concurrency.job_count() == 2
    assert args.dask_workers == 3  # the Dask cluster's size: another name, another number
    monkeypatch.delenv("GVBENCH_JOBS")
    assert cli.build_parser().parse_args(["run", "p.yaml"]).jobs is None
    monkeypatch.setenv("GVBENCH_JOBS", "0")
    with pytest.raises(SystemExit) as stopped:  # a bad variable is refused at parse time, before any work
        cli.build_parser().parse_args(["run", "p.yaml"])
    assert stopped.value.code == 2
    assert "argument --jobs: must be a whole number of at least 1 (--jobs or $GVBENCH_JOBS), got '0'" in (
        capsys.readouterr().err
    )
    monkeypatch.delenv("GVBENCH_JOBS")
    with pytest.raises(SystemExit):  # the old spelling is gone, not an alias
        cli.build_parser().parse_args(["run", "p.yaml", "--workers", "2"])
    assert "unrecognized arguments: --workers 2" in capsys.readouterr().err
