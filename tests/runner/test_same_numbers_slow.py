"""The same numbers on any split of the work, on the whole of Gardens Point: one job, two jobs, two
shards merged and a Dask cluster of two workers each write the same ``pairs.csv``, timers aside.
Every split starts from a fresh cache of its own, so each extracts, matches and verifies anew.
Each test is one method (and profile), so that a subset can be chosen: on a quiet 2-core CPU the
whole-sequence ones take about 2 (orb-nn) to 8 minutes (sift-nn) each, paper xfeat-nn about 20,
the learned ones 3 (aliked-nn) to 15 (xfeat-lg), each Dask one 2."""

import io
from pathlib import Path

import pandas as pd
import pytest

from gvbench_nb.runner import config, distributed, method_runs, sequence_build

PARAMS = config.PROJECT_ROOT / "params" / "gardens_point.yaml"
CHEAP_METHODS = ("sift-nn", "orb-nn", "xfeat-nn")
LEARNED_METHODS = ("aliked-nn", "xfeat-lg", "aliked-lg")
LEARNED_PAIRS = 100  # the learned methods' first pairs: a whole sequence of them is hours on a CPU
DASK_PAIRS = 40  # the Dask cluster's sample: its workers start processes of their own
# Past CI's time beside the rest of the slow tier (about 50 minutes of these on a quiet 2-core CPU):
# `make test-long` runs them; `make test-slow` runs the others.
LONG = {
    ("repository", "xfeat-nn"),
    ("paper", "sift-nn"),
    ("paper", "xfeat-nn"),
    ("paper", "xfeat-lg"),
    ("paper", "aliked-lg"),
}


def params_of(data: Path, folder: Path, profile: str, methods: tuple[str, ...], limit: int | None) -> dict:
    """The sequence's params with a pair file, an output folder and a fresh cache of the split's own."""
    return config.load_params(
        PARAMS,
        limit=limit,
        image_root=str(data / "gardens_point"),
        pairs=str(folder / "pairs.txt"),
        profile=profile,
        methods=list(methods),
        output_dir=str(folder / "out"),
        cache_dir=str(folder / "cache"),
    )


def pairs_without_timers(output: Path, method: str) -> str:
    """A finished run's ``pairs.csv`` as text, less the timer columns (the only ones that may differ)."""
    (found,) = output.glob(f"runs/*/{method}/pairs.csv")
    table = pd.read_csv(found, dtype=str, keep_default_na=False)
    return table[[c for c in table.columns if not c.endswith("_seconds")]].to_csv(index=False)


def run_split(
    data: Path, split: str, folder: Path, profile: str, methods: tuple[str, ...], limit: int | None
) -> dict[str, str]:
    """Every method's ``pairs.csv`` (timers aside) of one split of the work."""
    params = params_of(data, folder, profile, methods, limit)
    if split == "one job":
        sequence = sequence_build.prepare_sequence(params)
        for method in methods:
            method_runs.run_method_of_params(params, sequence, method, progress=False, jobs=1)
    elif split == "two jobs":
        sequence = sequence_build.prepare_sequence(params)
        for method in methods:
            method_runs.run_method_of_params(params, sequence, method, progress=False, jobs=2)
    elif split == "two shards":
        for index in (1, 0):
            distributed.run_shard(params, index, 2, progress=False)
        distributed.merge_runs(params)
    else:  # two Dask workers, each a process of its own
        distributed.run_sharded(params, n_shards=4, n_workers=2, processes=True, progress=False)
    return {method: pairs_without_timers(Path(params["output_dir"]), method) for method in methods}


def assert_every_split_equal(
    data: Path, tmp_path: Path, profile: str, methods: tuple[str, ...], limit: int | None
) -> None:
    tables = {
        split: run_split(data, split, tmp_path / split.replace(" ", "_"), profile, methods, limit)
        for split in ("one job", "two jobs", "two shards")
    }
    for method in methods:
        expected = tables["one job"][method]
        assert pd.read_csv(io.StringIO(expected))["num_matches"].astype(int).max() > 0  # something to compare
        for split in ("two jobs", "two shards"):
            assert tables[split][method] == expected, f"{method} ({profile}): {split} differs from one job"


@pytest.mark.slow
@pytest.mark.real_data
@pytest.mark.reliability
@pytest.mark.parametrize(
    ("profile", "method"),
    [
        pytest.param(profile, method, marks=[pytest.mark.long] if (profile, method) in LONG else [])
        for profile in ("repository", "paper")
        for method in CHEAP_METHODS
    ],
)
def test_whole_gardens_point_gives_one_table_on_one_job_two_jobs_and_two_shards(shared_data, tmp_path, profile, method):
    assert_every_split_equal(shared_data, tmp_path, profile, (method,), None)


@pytest.mark.slow
@pytest.mark.real_data
@pytest.mark.reliability
@pytest.mark.parametrize(
    "method", [pytest.param(m, marks=[pytest.mark.long] if ("paper", m) in LONG else []) for m in LEARNED_METHODS]
)
def test_learned_methods_give_one_table_on_one_job_two_jobs_and_two_shards(shared_data, tmp_path, method):
    assert_every_split_equal(shared_data, tmp_path, "paper", (method,), LEARNED_PAIRS)


@pytest.mark.slow
@pytest.mark.real_data
@pytest.mark.reliability
@pytest.mark.parametrize("profile", ["repository", "paper"])
def test_a_dask_cluster_of_two_workers_gives_the_one_job_table(shared_data, tmp_path, profile):
    methods = CHEAP_METHODS + LEARNED_METHODS[:1]
    one_job = run_split(shared_data, "one job", tmp_path / "one_job", profile, methods, DASK_PAIRS)
    assert run_split(shared_data, "dask", tmp_path / "dask", profile, methods, DASK_PAIRS) == one_job
