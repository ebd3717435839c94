"""notebooks/explore_pairs: the pair it shows, each method's score and rank, from cached results only."""

from __future__ import annotations

import json
from pathlib import Path

import pandas as pd
import pytest
import yaml

from gvbench_nb import config, pipeline
from gvbench_nb.evaluation import explore

NOTEBOOKS = Path(__file__).resolve().parent.parent / "notebooks"
METHODS = ["sift-nn", "orb-nn"]


def expected_rank(table: pd.DataFrame, index: int) -> int:
    """1 + the pairs scoring strictly higher: the rank as the notebook defines it."""
    return int(1 + (table["score"] > table["score"].iloc[index]).sum())


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory) -> Path:
    """sift-nn and orb-nn on the synthetic route, 6 frames of 160x120 (36 pairs, 4 false)."""
    folder = tmp_path_factory.mktemp("explore")
    params = {
        "sequence": "tiny",
        "pairs_builder": "sample",
        "builder_options": {"n_frames": 6, "image_size": [160, 120]},
        "image_root": str(folder / "data"),
        "pairs": str(folder / "data" / "pairs.txt"),
        "methods": METHODS,
        "profile": "repository",
        "output_dir": str(folder / "out"),
        "seed": 0,
    }
    path = folder / "tiny.yaml"
    path.write_text(yaml.safe_dump(params))
    loaded = config.load_params(path)
    sequence = config.prepare_sequence(loaded)
    for method in METHODS:
        pipeline.run_method(
            sequence,
            method,
            "repository",
            Path(loaded["output_dir"]),
            Path(loaded["cache_dir"]),
            device="cpu",
            progress=False,
            threads=1,
        )
    return path


def test_score_ranks_share_the_best_rank_of_a_tie():
    table = pd.DataFrame({"score": [5, 9, 5, 0, 9]})
    assert list(explore.score_ranks(table)) == [3, 1, 3, 5, 1]


def test_choose_pair_by_index_and_by_a_methods_failures():
    table = pd.DataFrame({"pair_index": range(5), "label": [1, 0, 1, 0, 1], "score": [3, 7, 1, 7, 9]})
    tables = {"a": table, "b": table.assign(score=[0, 1, 2, 3, 4])}
    assert explore.choose_pair(tables, "index", 2) == 2
    assert explore.choose_pair(tables, "false_positive") == 1  # tie at 7: the lower pair_index first
    assert explore.choose_pair(tables, "false_positive", pick_rank=2) == 3
    assert explore.choose_pair(tables, "false_negative", pick_method="b") == 0
    with pytest.raises(ValueError, match="pair_index must be a pair of the run, 0 to 4"):
        explore.choose_pair(tables, "index", 5)
    with pytest.raises(ValueError, match="fewer than pick_rank 3"):
        explore.choose_pair(tables, "false_positive", pick_rank=3)
    with pytest.raises(ValueError, match="not among the methods shown"):
        explore.choose_pair(tables, "false_negative", pick_method="c")


def test_widgets_only_when_asked_or_live():
    assert explore.use_widgets("none") is False
    with pytest.raises(ValueError, match="controls must be"):
        explore.use_widgets("sometimes")
    assert explore.use_widgets("auto") is False  # a pytest process is no live kernel


@pytest.mark.slow
def test_explore_notebook_shows_the_scores_and_ranks_of_pairs_csv(tiny_run, tmp_path):
    import papermill

    figures = tmp_path / "figures"
    executed = tmp_path / "explore_pairs.ipynb"
    papermill.execute_notebook(
        str(NOTEBOOKS / "explore_pairs.ipynb"),
        str(executed),
        cwd=str(NOTEBOOKS),
        kernel_name="python3",
        progress_bar=False,
        parameters={
            "params_file": str(tiny_run),
            "methods": METHODS,
            "pick": "false_positive",
            "pick_method": "orb-nn",
            "figures_dir": str(figures),
        },
    )
    shown = pd.read_csv(figures / "explore_pair.csv")
    out = tiny_run.parent / "out"
    tables = {m: pd.read_csv(out / m / "pairs.csv") for m in METHODS}
    false = tables["orb-nn"][tables["orb-nn"]["label"] == 0]
    top = false.sort_values(["score", "pair_index"], ascending=[False, True], kind="mergesort").iloc[0]
    index = int(top["pair_index"])
    assert list(shown["method"]) == METHODS and set(shown["pair_index"]) == {index}
    for row in shown.itertuples():
        table = tables[row.method]
        assert (row.query, row.reference, row.label) == tuple(table.loc[index, ["query", "reference", "label"]])
        assert row.score == table["score"].iloc[index] == table["num_inliers"].iloc[index]
        assert row.rank == expected_rank(table, index) and row.n_pairs == len(table)
        assert row.max_false_score == table.loc[table["label"] == 0, "score"].max()
    assert (figures / f"explore_pair_{index}.png").is_file() and (figures / f"explore_scores_{index}.png").is_file()
    # Under papermill the controls cell draws no widgets and says so.
    last = json.loads(executed.read_text())["cells"][-1]
    assert "controls: none" in "".join("".join(o.get("text", "")) for o in last["outputs"])
