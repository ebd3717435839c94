"""Sharded runs (by hand and through Dask) merge into exactly the unsharded result."""

from pathlib import Path

import pandas as pd
import pytest
import yaml

from gvbench_nb import methods
from gvbench_nb.data.sequences import Pair, write_pairs
from gvbench_nb.runner import config, distributed, image_features, method_runs, scoring

METHOD, PROFILE = "sift-nn", "repository"


def twelve_pairs() -> list[Pair]:
    """Three day queries, each with two true neighbouring frames and two false ones (12 pairs).
    Day frames: COLMAP SIFT finds hardly any night-to-day matches at 512 px, so no inliers."""
    pairs = []
    for q in (30, 90, 150):
        for r, label in ((q + 1, 1), (q + 2, 1), ((q + 50) % 200, 0), ((q + 100) % 200, 0)):
            pairs.append(Pair(f"day_right/Image{q:03d}.jpg", f"day_right/Image{r:03d}.jpg", label))
    return pairs


def make_params(shared_data: Path, folder: Path) -> dict:
    """A params file of its own (own output and cache folders) over the same pair file."""
    folder.mkdir(parents=True, exist_ok=True)
    pairs = folder.parent / "pairs.txt"
    if not pairs.is_file():
        write_pairs(pairs, twelve_pairs())
    path = folder / "params.yaml"
    path.write_text(
        yaml.safe_dump(
            {
                "sequence": "gp_shards",
                "pairs": str(pairs),
                "image_root": str(shared_data / "gardens_point"),
                "methods": [METHOD],
                "profile": PROFILE,
                "output_dir": str(folder / "out"),
                "cache_dir": str(folder / "cache"),
            }
        )
    )
    return config.load_params(path)


def without_timings(table: pd.DataFrame) -> pd.DataFrame:
    return table[[c for c in table.columns if not c.endswith("_seconds")]]


@pytest.fixture(scope="module")
def unsharded(shared_data, tmp_path_factory) -> pd.DataFrame:
    params = make_params(shared_data, tmp_path_factory.mktemp("runs") / "unsharded")
    method_runs.run_method(
        config.prepare_sequence(params),
        METHOD,
        PROFILE,
        Path(params["output_dir"]),
        Path(params["cache_dir"]),
        progress=False,
    )
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
    assert len(store) == len(config.prepare_sequence(params).images)


@pytest.mark.real_data
def test_merge_with_a_missing_shard_names_the_missing_pairs(shared_data, tmp_path):
    params = make_params(shared_data, tmp_path / "partial")
    distributed.run_shard(params, 0, 3, threads=1, progress=False)
    with pytest.raises(distributed.ShardError, match=r"8 of 12 pairs have no result.*first: pair 1, "):
        distributed.merge_runs(params)
    assert not (Path(params["output_dir"]) / METHOD / "pairs.csv").exists()


def test_pair_shards_partition_the_pairs():
    from gvbench_nb.data.sequences import Sequence

    sequence = Sequence("s", Path("/images"), twelve_pairs())
    shards = [distributed.pair_shard(sequence, i, 5) for i in range(5)]
    assert sorted((p for s in shards for p in s.pairs), key=sequence.pairs.index) == sequence.pairs


@pytest.mark.parametrize("text", ["3/3", "-1/2", "1", "a/b", "0/0"])
def test_parse_shard_rejects_bad_values(text):
    with pytest.raises(ValueError, match="shard"):
        distributed.parse_shard(text)


def test_parse_shard_reads_index_and_count():
    assert distributed.parse_shard("2/5") == (2, 5)
