"""AP and MR intervals resample queries, not pairs, and rankings come from paired resamples."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
from sklearn.metrics import average_precision_score

from gvbench_nb.evaluation import bootstrap, run_tables
from gvbench_nb.protocol import metrics


def pairs_frame(queries, references, labels, scores) -> pd.DataFrame:
    return pd.DataFrame({"query": queries, "reference": references, "label": labels, "score": scores})


def identical_queries(n_queries: int = 40) -> pd.DataFrame:
    """Every query has the same three pairs (true 3, false 2, true 1): a draw of whole queries never
    moves AP (5/6) or MR (1/2); a draw of single pairs changes their mix, and both metrics with it."""
    queries = np.repeat([f"q{i}" for i in range(n_queries)], 3)
    references = [f"r{i}" for i in range(3 * n_queries)]
    return pairs_frame(queries, references, np.tile([1, 0, 1], n_queries), np.tile([3.0, 2.0, 1.0], n_queries))


def noisy_queries(seed: int, n_queries: int = 60, per_query: int = 5) -> pd.DataFrame:
    rng = np.random.default_rng(seed)
    n = n_queries * per_query
    labels = (rng.random(n) < 0.4).astype(int)
    labels[0], labels[1] = 1, 0
    queries = np.repeat([f"q{i}" for i in range(n_queries)], per_query)
    return pairs_frame(queries, [f"r{i}" for i in range(n)], labels, rng.normal(labels, 1.0))


def query_intervals(tables: dict[str, pd.DataFrame], n_resamples: int, seed: int = 0) -> pd.DataFrame:
    return bootstrap.intervals_of(bootstrap.bootstrap(tables, n_resamples, seed))


def test_intervals_resample_queries_not_pairs():
    table = identical_queries()
    result = query_intervals({"m": table}, n_resamples=300, seed=0).set_index("method")
    row = result.loc["m"]
    assert row["ap"] == pytest.approx(average_precision_score(table["label"], table["score"]))
    assert row["ap"] == pytest.approx(5 / 6)
    assert row["max_recall"] == pytest.approx(metrics.max_recall_at_full_precision(table["label"], table["score"]))
    for metric in ("ap", "max_recall"):
        assert row[f"{metric}_low"] == pytest.approx(row[metric])
        assert row[f"{metric}_high"] == pytest.approx(row[metric])
    assert row["interval_unit"] == "query"
    assert (row["n_queries"], row["n_pairs"], row["n_resamples"]) == (40, 120, 300)

    # The same data resampled pair by pair: the intervals this test rules out are wide.
    by_pair = bootstrap.query_resample_weights(np.arange(len(table)), 300, seed=0)
    ap, max_recall = bootstrap.weighted_ap_max_recall(table["label"].to_numpy(), table["score"].to_numpy(), by_pair)
    assert np.nanpercentile(ap, 97.5) - np.nanpercentile(ap, 2.5) > 0.05
    assert np.nanpercentile(max_recall, 97.5) - np.nanpercentile(max_recall, 2.5) > 0.1


def test_intervals_are_deterministic_for_a_seed():
    tables = {"a": noisy_queries(0), "b": noisy_queries(0).assign(score=lambda t: t["score"] + t["label"])}
    first = query_intervals(tables, 200, seed=3)
    pd.testing.assert_frame_equal(first, query_intervals(tables, 200, seed=3))
    other = query_intervals(tables, 200, seed=4)
    assert not np.allclose(first[["ap_low", "ap_high"]], other[["ap_low", "ap_high"]])
    assert first["seed"].tolist() == [3, 3]
    shares = [bootstrap.bootstrap(tables, 200, seed=3).paired_shares("ap") for _ in range(2)]
    pd.testing.assert_frame_equal(*shares)


def test_a_consistent_small_loss_is_ranked_though_the_intervals_overlap():
    better = noisy_queries(1)
    # Every false pair moves up: no pair order improves, so B is at best equal on any draw.
    worse = better.assign(score=better["score"] + 0.1 * (1 - better["label"]))
    boot = bootstrap.bootstrap({"better": better, "worse": worse}, 500, seed=0)
    table = bootstrap.intervals_of(boot).set_index("method")
    assert table.loc["worse", "ap_high"] > table.loc["better", "ap_low"]  # the intervals alone: a tie
    shares = boot.paired_shares("ap").iloc[0]
    assert (shares["first"], shares["second"]) == ("better", "worse")
    assert shares["first_beats_second"] >= 0.95
    assert shares["second_beats_first"] == 0.0
    assert shares["verdict"] == "better > worse"

    # Drawn apart (an unpaired bootstrap), the same two methods would read as a tie.
    apart = bootstrap.bootstrap({"worse": worse}, 500, seed=1).samples["ap"]["worse"]
    assert np.mean(boot.samples["ap"]["better"].to_numpy() > apart.to_numpy()) < 0.8


def test_same_ranking_is_tied_in_every_paired_resample_and_a_better_one_ranked_first():
    table = noisy_queries(2)
    rescaled = table.assign(score=2 * table["score"] + 1)  # the same order of pairs
    boot = bootstrap.bootstrap({"a": table, "b": rescaled}, 300, seed=0)
    for metric in ("ap", "max_recall"):
        shares = boot.paired_shares(metric).iloc[0]
        assert shares["tied"] == 1.0
        assert shares["first_beats_second"] == shares["second_beats_first"] == 0.0
        assert shares["verdict"] == "tie"
    # A ranking in either direction: the leader on all pairs is first.
    table = noisy_queries(3)
    perfect = table.assign(score=table["label"] * 10.0)
    boot = bootstrap.bootstrap({"weak": table, "perfect": perfect}, 300, seed=0)
    shares = boot.paired_shares("max_recall").iloc[0]
    assert (shares["first"], shares["second"], shares["verdict"]) == ("perfect", "weak", "perfect > weak")
    assert shares["first_value"] == 1.0
    assert boot.intervals().set_index(["method", "metric"]).loc[("perfect", "max_recall"), "low"] == 1.0
    # The leader on all pairs is listed first even when it is given second.
    reversed_boot = bootstrap.bootstrap({"perfect": perfect, "weak": table}, 300, seed=0)
    assert reversed_boot.paired_shares("max_recall").iloc[0]["first"] == "perfect"


def test_interval_columns_keyed_by_method():
    tables = {"a": noisy_queries(4), "b": noisy_queries(4).assign(score=lambda t: -t["score"])}
    columns = bootstrap.interval_columns(tables, 200, seed=0)
    assert list(columns.index) == ["a", "b"]
    assert list(columns.columns) == ["ap_low", "ap_high", "max_recall_low", "max_recall_high", "interval_unit"]
    full = query_intervals(tables, 200, seed=0).set_index("method")
    pd.testing.assert_frame_equal(columns, full[list(columns.columns)])
    assert (columns["ap_low"] <= full["ap"]).all() and (full["ap"] <= columns["ap_high"]).all()
    # Methods run on different pairs still get their own intervals, over their own queries.
    shorter = bootstrap.interval_columns({"a": tables["a"], "c": tables["a"].iloc[:100]}, 200, seed=0)
    pd.testing.assert_series_equal(shorter.loc["a"], columns.loc["a"])
    assert (
        shorter.loc["c", "ap_high"] - shorter.loc["c", "ap_low"]
        > columns.loc["a", "ap_high"] - columns.loc["a", "ap_low"]
    )


def test_refuses_methods_with_different_labels():
    table = noisy_queries(5)
    relabelled = table.assign(label=1 - table["label"])
    with pytest.raises(run_tables.IncomparableRunsError, match="label 300 of the same pairs differently"):
        query_intervals({"a": table, "b": relabelled}, 100)
    with pytest.raises(run_tables.IncomparableRunsError, match="scored different pairs"):
        query_intervals({"a": table, "b": table.iloc[:-5]}, 100)


def test_the_notebooks_matrix_and_compares_table_rank_by_one_rule():
    # A wins 96 of 100 draws: ranked at the rule's 95 %, where a 97.5 % reading would call a tie.
    samples = pd.DataFrame({"a": [0.6] * 96 + [0.4] * 4, "b": [0.5] * 100})
    boot = bootstrap.Bootstrap(
        methods=["a", "b"],
        estimates=pd.DataFrame({"ap": [0.6, 0.5], "max_recall": [0.6, 0.5]}, index=["a", "b"]),
        samples={"ap": samples, "max_recall": samples},
        n_queries=10,
        n_pairs=20,
        seed=0,
    )
    assert boot.paired_shares("ap").iloc[0]["verdict"] == "a > b"
    matrix = boot.ranking_matrix("ap")
    assert (matrix.loc["a", "b"], matrix.loc["b", "a"]) == (">", "<")
    tied = boot.paired_shares("ap", ranked_share=0.975).iloc[0]["verdict"]
    assert tied == "tie" and boot.ranking_matrix("ap", ranked_share=0.975).loc["a", "b"] == "~"
