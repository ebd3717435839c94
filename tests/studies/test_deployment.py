"""Threshold transfer and the loop-closure level, on hand-made tables whose answers are worked
out below by hand, and the reader's refusals (those of ``results``)."""

from __future__ import annotations

import shutil

import numpy as np
import pandas as pd
import pytest
from written_runs import add_run

from gvbench_nb import cli
from gvbench_nb.protocol import metrics
from gvbench_nb.runner import method_outputs, runs, scoring
from gvbench_nb.studies import deployment

# Calibration: the false scores are 7, 3, 2; the scores above 7 are 10 and 12, so the threshold is
# 10; the true pair scored 7 ties the highest false one and stays below it.
CALIBRATION = {"label": [1, 1, 1, 0, 0, 1, 0], "score": [10, 7, 5, 7, 3, 12, 2]}
# Target at threshold 10: accepted 11 (true), 10 (false), 15 (false), 10 (true): precision 2/4,
# recall 2/3, two false loops.
TARGET = {"label": [1, 0, 1, 0, 1], "score": [11, 10, 9, 15, 10]}


def test_oracle_threshold_is_the_smallest_score_above_every_false_one_and_transfers():
    assert deployment.oracle_threshold(CALIBRATION["label"], CALIBRATION["score"]) == 10
    assert deployment.oracle_threshold([1, 0], [4, 4]) == float("inf")  # a tie at the top: nothing passes
    assert deployment.oracle_threshold([1, 0, 1], [2.5, 1.0, 1.5]) == 1.5
    # Applied to the target, it counts what it accepts there.
    applied = deployment.apply_threshold(TARGET["label"], TARGET["score"], 10)
    assert applied == {"precision": 0.5, "recall": pytest.approx(2 / 3), "false_loops": 2, "n_accepted": 4}
    nothing = deployment.apply_threshold(TARGET["label"], TARGET["score"], float("inf"))
    assert np.isnan(nothing["precision"]) and nothing["recall"] == 0 and nothing["false_loops"] == 0


@pytest.mark.parametrize("seed", range(5))
def test_the_threshold_gives_mr_on_its_own_sequence(seed):
    # The rule agrees with MR as metrics.py computes it (scikit-learn's PR curve), ties included.
    rng = np.random.default_rng(seed)
    labels = rng.integers(0, 2, 60)
    labels[:2] = (0, 1)
    scores = rng.integers(0, 12, 60) + 4 * labels
    threshold = deployment.oracle_threshold(labels, scores)
    applied = deployment.apply_threshold(labels, scores, threshold)
    assert applied["recall"] == pytest.approx(metrics.max_recall_at_full_precision(labels, scores))
    assert applied["false_loops"] == 0


def pairs_table(queries, labels, scores) -> pd.DataFrame:
    return pd.DataFrame(
        {
            "pair_index": range(len(queries)),
            "query": queries,
            "reference": [f"r{i}" for i in range(len(queries))],
            "label": labels,
            "score": scores,
        }
    )


def test_query_outcomes_rerank_by_score_and_keep_file_order_on_ties():
    # q0: retrieval puts a false first (score 3), GV ranks the true (9) first.
    # q1: the true is first, but a false scores higher (8 > 6): GV puts the false first.
    # q2: no true candidate. q3: both score 5; the first in file order (true) stays first.
    table = pairs_table(["q0", "q0", "q1", "q1", "q2", "q3", "q3"], [0, 1, 1, 0, 0, 1, 0], [3, 9, 6, 8, 2, 5, 5])
    outcomes = deployment.query_outcomes(table, threshold=6)
    assert outcomes["has_true"].tolist() == [True, True, False, True]
    assert outcomes["first_true"].tolist() == [False, True, False, True]
    assert outcomes["best_true"].tolist() == [True, False, False, True]
    assert outcomes["best_passes"].tolist() == [True, True, False, False]


def write_run(
    folder, sequence: str, labels, scores, builder: str = "frame_tolerance", methods=("sift-nn",), profile="repository"
) -> None:
    """Finished methods' files as a run writes them, evaluated into a published results.csv."""
    for method in methods:
        write_method(folder, method, sequence, labels, scores, builder, profile)
    scoring.evaluate(folder)


def write_method(folder, method: str, sequence: str, labels, scores, builder: str, profile: str) -> None:
    queries = [f"q{i // 2}" for i in range(len(labels))]
    table = pairs_table(queries, labels, scores).assign(extract_seconds=0.1, match_seconds=0.1, verify_seconds=0.1)
    run = {
        "sequence": sequence,
        "conf": {"paper_name": method, "profile": profile},
        "pairs": {"pairs_builder": builder},
    }
    add_run(folder, method, table, run)


def test_transfer_reads_finished_runs_and_prints_the_matrix(tmp_path, capsys):
    # day: false 4, 1; true 9, 6 -> threshold 6. night at 6: true 7 and false 8 pass.
    write_run(tmp_path / "day", "day", [1, 0, 1, 0], [9, 4, 6, 1], builder="retrieval")
    write_run(tmp_path / "night", "night", [0, 1, 1, 0], [8, 7, 2, 3])
    inputs = deployment.DeploymentInputs([tmp_path / "day", tmp_path / "night"])
    table = deployment.transfer_table(inputs)
    night = table[(table.calibration == "day") & (table.target == "night")].iloc[0]
    assert (night.threshold, night.precision, night.recall, night.false_loops) == (6, 0.5, 0.5, 1)
    loops = deployment.loop_closure_table(table, inputs).set_index(["calibration", "target"])
    # night, q0: best is the false 8 (passes 6): a false loop; q1: best is the false 3 (below 6).
    assert loops.loc[("day", "night"), "false_loops_closed"] == 1
    assert loops.loc[("day", "night"), "recall_at_1_gv"] == 0.0
    assert np.isnan(loops.loc[("day", "night"), "recall_at_1_retrieval"])  # rule-built: no retrieval order
    assert loops.loc[("day", "day"), "recall_at_1_retrieval"] == 1.0  # retrieval-built: file order kept
    assert cli.main(["transfer", str(tmp_path / "day"), str(tmp_path / "night")]) == 0
    printed = capsys.readouterr().out
    assert "transfer" in cli.build_parser().format_help()  # its help line formats
    assert "day (threshold 6)" in printed and "0.500 / 0.500 / 1" in printed and "1.000 / 1.000 / 0" in printed


def test_transfer_refuses_what_results_refuses(tmp_path, capsys):
    write_run(tmp_path / "day", "day", [1, 0, 1, 0], [9, 4, 6, 1])
    # night's pair file changed since its run: its scores are no longer of its pairs.
    pair_file = tmp_path / "night.txt"
    pair_file.write_text("q0 r0 1\n")
    table = pairs_table(["q0", "q0", "q1", "q1"], [0, 1, 1, 0], [8, 7, 2, 3])
    pairs = {"pairs_builder": "frame_tolerance", "pairs_file": str(pair_file), "pairs_sha256": "0" * 64}
    run = {"sequence": "night", "conf": {"paper_name": "sift-nn", "profile": "repository"}, "pairs": pairs}
    add_run(
        tmp_path / "night", "sift-nn", table.assign(extract_seconds=0.1, match_seconds=0.1, verify_seconds=0.1), run
    )
    with pytest.raises(method_outputs.ResultsError, match="the pair file"):
        deployment.DeploymentInputs([tmp_path / "day", tmp_path / "night"])
    shutil.rmtree(tmp_path / "day" / runs.RUNS)  # and a folder of the earlier layout
    (tmp_path / "day" / runs.OLD_RECORD).write_text("{}")
    with pytest.raises(runs.RunsError, match="python -m gvbench_nb upgrade"):
        deployment.DeploymentInputs([tmp_path / "day"])
    capsys.readouterr()
    for folder in ("night", "day"):
        assert cli.main(["results", str(tmp_path / folder)]) == 2
        assert cli.main(["transfer", str(tmp_path / folder), str(tmp_path / folder)]) == 2
    message = capsys.readouterr().err.strip().splitlines()
    assert len(message) == 4 and all(line.startswith("error: ") for line in message)
    assert message[0] == message[1] and message[2] == message[3]


@pytest.mark.reliability
def test_transfer_names_every_method_and_target_it_could_not_do_and_exits_3(tmp_path, capsys):
    write_run(tmp_path / "day", "day", [1, 0, 1, 0], [9, 4, 6, 1], methods=("sift-nn", "orb-nn"))
    write_run(tmp_path / "night", "night", [0, 1, 1, 0], [8, 7, 2, 3])  # no orb-nn
    write_run(tmp_path / "dusk", "dusk", [0, 1, 1, 0], [8, 7, 2, 3], profile="paper")  # another profile
    capsys.readouterr()
    code = cli.main(["transfer", *(str(tmp_path / f) for f in ("day", "night", "dusk"))])
    said = capsys.readouterr()
    assert code == deployment.NOT_ALL_DONE == 3
    assert "sift-nn (repository profile)" in said.out  # what could be done is printed
    not_done = [line for line in said.err.splitlines() if line.startswith("not done: ")]
    assert len(not_done) == 4, said.err
    assert "orb-nn (repository profile, calibrated on day): not transferred to night, which has no results" in said.err
    assert "not transferred to dusk, which holds it under the paper profile" in said.err
    assert "not done: target dusk left out" in said.err
    assert cli.main(["transfer", str(tmp_path / "night"), str(tmp_path / "night")]) != 0  # a sequence twice
    assert cli.main(["transfer", str(tmp_path / "dusk"), str(tmp_path / "night")]) == 3
    assert "not done: target night left out" in capsys.readouterr().err


@pytest.mark.reliability
def test_a_method_the_calibration_holds_under_two_profiles_transfers_to_a_target_holding_one(tmp_path):
    """The calibration folder labels its orb-nn rows by profile; the target, holding one, by name
    alone: the transfer still pairs the runs of one method and profile across the folders."""
    for profile in ("repository", "paper"):
        write_method(tmp_path / "day", "orb-nn", "day", [1, 0, 1, 0], [9, 4, 6, 1], "frame_tolerance", profile)
    write_method(tmp_path / "night", "orb-nn", "night", [0, 1, 1, 0], [8, 7, 2, 3], "frame_tolerance", "repository")
    inputs = deployment.DeploymentInputs([tmp_path / "day", tmp_path / "night"])
    table = deployment.transfer_table(inputs)
    crossed = table[(table.calibration == "day") & (table.target == "night")]
    assert crossed[["method", "profile"]].values.tolist() == [["orb-nn", "repository"]]
    assert crossed.iloc[0]["recall"] == pytest.approx(0.5)  # threshold 6: true 7 passes, true 2 does not
    left = deployment.not_transferred(inputs, inputs.sequences, table)
    assert any("paper" in line and "night" in line for line in left)
