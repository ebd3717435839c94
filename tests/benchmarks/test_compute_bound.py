"""benchmarks/compute_bound.py: the one-core run's timers, summed and shared over the cores."""

import compute_bound
import pandas as pd
import pytest

from gvbench_nb.runner import method_outputs


@pytest.mark.shared_outputs  # renders params/sample.yaml's images into outputs/sample
@pytest.mark.slow
def test_the_bound_is_the_one_core_work_shared_over_the_cores(tmp_path, capsys):
    options = ["--method", "orb-nn", "--limit", "12", "--cores", "3", "--peer-seconds", "9", "--out", str(tmp_path)]
    assert compute_bound.main(["params/sample.yaml", *options]) == 0
    row = pd.read_csv(tmp_path / "compute_bound.csv").iloc[0]
    folder = method_outputs.method_dir(tmp_path / "run" / "output", "orb-nn")
    pairs = pd.read_csv(folder / "pairs.csv")
    run = pd.read_json(folder / "run.json", typ="series")
    assert run["this_run"]["jobs"] == 1 and run["this_run"]["threads"] == 1  # one job on one thread
    assert row["n_pairs"] == len(pairs) == 12
    work = sum(pairs[name].sum() for name in compute_bound.TIMERS)
    assert row["one_core_work_seconds"] == pytest.approx(work, abs=0.01) and work > 0
    assert row["bound_wall_seconds"] == pytest.approx(work / 3, abs=0.01)
    assert row["largest_speedup_over_peer"] == pytest.approx(9 / (work / 3), rel=0.01)
