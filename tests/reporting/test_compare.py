"""``python -m gvbench_nb compare``: intervals over queries, paired shares and verdicts, and
one-sentence refusals of methods that cannot be compared."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
from written_runs import add_run

from gvbench_nb import cli


def noisy_table(seed: int = 0, n_queries: int = 50, per_query: int = 4) -> pd.DataFrame:
    rng = np.random.default_rng(seed)
    n = n_queries * per_query
    labels = (rng.random(n) < 0.4).astype(int)
    labels[0], labels[1] = 1, 0
    queries = np.repeat([f"q{i}" for i in range(n_queries)], per_query)
    table = {"pair_index": range(n), "query": queries, "reference": [f"r{i}" for i in range(n)], "label": labels}
    timers = {"extract_seconds": 0.1, "match_seconds": 0.1, "verify_seconds": 0.1}
    return pd.DataFrame(table | {"score": rng.normal(labels, 1.0)} | timers)


def write_run(output_dir, method: str, table: pd.DataFrame, profile: str = "repository") -> None:
    add_run(output_dir, method, table, {"conf": {"paper_name": method.upper(), "profile": profile}})


@pytest.fixture
def folder(tmp_path):
    table = noisy_table()
    write_run(tmp_path / "toy", "sift-nn", table)
    write_run(tmp_path / "toy", "xfeat-nn", table.assign(score=table["label"] * 10.0))  # perfect
    write_run(tmp_path / "toy", "orb-nn", table.assign(score=3 * table["score"]))  # sift-nn's order
    return tmp_path / "toy"


def test_compare_prints_intervals_over_queries_and_paired_verdicts(folder, capsys):
    assert cli.main(["compare", str(folder), "--resamples", "200", "--seed", "1"]) == 0
    out = capsys.readouterr().out
    assert "95 % percentile intervals over 50 queries resampled with replacement (200 resamples, seed 1)" in out
    assert "max_recall_low" in out and "ap_high" in out
    lines = out.splitlines()
    verdicts = [line.split()[-3:] for line in lines if line.split()[:1] in (["ap"], ["max_recall"])]
    assert len(verdicts) == 6  # three pairs a metric
    # xfeat-nn is perfect: ranked over both; sift-nn and orb-nn order every pair alike: a tie.
    assert ["xfeat-nn", ">", "sift-nn"] in verdicts and ["xfeat-nn", ">", "orb-nn"] in verdicts
    same = [line.split() for line in lines if "sift-nn" in line and "orb-nn" in line and "xfeat-nn" not in line]
    assert len(same) == 2 and all(row[-1] == "tie" and row[-4] == row[-2] == "0.000" for row in same)


def test_compare_is_deterministic_and_takes_one_metric(folder, capsys):
    args = ["compare", str(folder), "--metric", "max_recall", "--resamples", "150", "--markdown"]
    assert cli.main(args) == 0
    first = capsys.readouterr().out
    assert cli.main(args) == 0
    assert capsys.readouterr().out == first
    assert "| max_recall | xfeat-nn |" in first and not any(line.startswith("| ap |") for line in first.splitlines())


def refused(capsys, argv) -> str:
    assert cli.main(argv) == 2
    captured = capsys.readouterr()
    assert captured.out == ""
    message = captured.err.strip()
    assert message.startswith("error: ") and "\n" not in message and "Traceback" not in message
    return message


@pytest.mark.parametrize(
    "other",
    [lambda t: t.assign(label=np.roll(t["label"], 1)), lambda t: t.iloc[:-8]],
    ids=["different labels", "different pairs"],
)
def test_compare_refuses_methods_on_different_pairs_or_labels(tmp_path, capsys, other):
    table = noisy_table()
    write_run(tmp_path / "toy", "sift-nn", table)
    write_run(tmp_path / "toy", "orb-nn", other(table))
    message = refused(capsys, ["compare", str(tmp_path / "toy")])
    # the sentence `results` gives: one function decides for every reader
    assert "scored on different pairs or labels (sift-nn: pairs" in message and "orb-nn: pairs" in message


def test_compare_refuses_a_folder_it_cannot_compare(tmp_path, capsys):
    assert "does not exist" in refused(capsys, ["compare", str(tmp_path / "absent")])
    write_run(tmp_path / "toy", "sift-nn", noisy_table())
    assert "one method only" in refused(capsys, ["compare", str(tmp_path / "toy")])
    assert "'orb-nn'" in refused(capsys, ["compare", str(tmp_path / "toy"), "--methods", "sift-nn,orb-nn"])


def test_compare_refuses_too_few_resamples(folder, capsys):
    with pytest.raises(SystemExit) as exit:
        cli.main(["compare", str(folder), "--resamples", "10"])
    assert exit.value.code == 2
    assert "at least 100" in capsys.readouterr().err


def test_compare_takes_methods_from_several_folders_of_the_same_pairs(tmp_path, capsys):
    table = noisy_table()
    write_run(tmp_path / "one", "sift-nn", table)
    write_run(tmp_path / "two", "xfeat-lg", table.assign(score=table["label"] * 10.0))
    assert cli.main(["compare", str(tmp_path / "one"), str(tmp_path / "two"), "--resamples", "100"]) == 0
    assert "xfeat-lg > sift-nn" in capsys.readouterr().out
    write_run(tmp_path / "three", "sift-nn", table)
    message = refused(capsys, ["compare", str(tmp_path / "one"), str(tmp_path / "three")])
    assert "'sift-nn' has results in both" in message
