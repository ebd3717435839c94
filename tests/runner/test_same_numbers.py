"""The same numbers on any split of the work: a run's table and its caches do not depend on how many
jobs it ran or on how many threads each job had."""

import io
import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from gvbench_nb.data.sequences import Pair, Sequence
from gvbench_nb.runner import method_runs
from gvbench_nb.runner.store import ShardedStore

METHOD, PROFILE = "xfeat-nn", "paper"


def pairs_without_timers(output: Path, method: str) -> str:
    """A run's ``pairs.csv`` as text, less the timer columns (the only ones that may differ)."""
    (found,) = output.glob(f"runs/*/{method}/pairs.csv")
    table = pd.read_csv(found, dtype=str, keep_default_na=False)
    return table[[c for c in table.columns if not c.endswith("_seconds")]].to_csv(index=False)


def store_entries(cache: Path, kind: str) -> dict[str, dict]:
    """Every entry of the cache's one ``kind`` store (features, matches), less its timers."""
    (folder,) = (cache / kind).iterdir()
    store = ShardedStore(folder)
    entries = {key: store.read(key) for key in store.keys()}
    store.close()
    return {key: {f: v for f, v in entry.items() if not f.endswith("seconds")} for key, entry in entries.items()}


def assert_same_entries(got: dict[str, dict], expected: dict[str, dict]) -> None:
    assert got.keys() == expected.keys()
    for key, entry in expected.items():
        assert got[key].keys() == entry.keys()
        for field, value in entry.items():
            assert np.array_equal(got[key][field], value), f"{field} of {key} differs between the splits"


@pytest.mark.real_data
@pytest.mark.reliability
def test_paper_profile_gives_the_same_table_and_caches_with_one_job_on_two_threads_or_two_jobs_on_one(
    shared_data, tmp_path
):
    # Two real night-to-day pairs whose XFeat keypoints hold near-equal scores: when the model's
    # convolutions round by the thread count, their order, the matches and the inliers move.
    pairs = [
        Pair("night_right/Image000.jpg", "day_right/Image010.jpg", 0),
        Pair("night_right/Image001.jpg", "day_right/Image002.jpg", 1),
    ]
    sequence = Sequence("gp_split", shared_data / "gardens_point", pairs)
    splits = {"one_job": {"jobs": 1, "threads": 2}, "two_jobs": {"jobs": 2, "threads": 1}}
    for name, split in splits.items():  # each split with a fresh cache of its own
        folder = tmp_path / name
        method_runs.run_method(
            sequence, METHOD, PROFILE, folder / "out", folder / "cache", device="cpu", progress=False, **split
        )
    one, two = tmp_path / "one_job", tmp_path / "two_jobs"
    table = pairs_without_timers(one / "out", METHOD)
    assert (pd.read_csv(io.StringIO(table))["num_inliers"].astype(int) > 0).all()
    assert pairs_without_timers(two / "out", METHOD) == table
    for kind in ("features", "matches"):
        assert_same_entries(store_entries(two / "cache", kind), store_entries(one / "cache", kind))
    # A run served from the other split's cache holds what it would have computed; its jobs are its own.
    served = tmp_path / "served"
    method_runs.run_method(
        sequence, METHOD, PROFILE, served, two / "cache", device="cpu", progress=False, **splits["one_job"]
    )
    assert pairs_without_timers(served, METHOD) == table
    (run,) = served.glob(f"runs/*/{METHOD}/run.json")
    this_run = json.loads(run.read_text())["this_run"]
    assert this_run["jobs"] == 1 and this_run["matching"] == {"pairs": 2, "cached": 2, "matched": 0}
