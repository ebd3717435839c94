"""The explorer and the analysis notebooks take a folder holding an imported method (``import-scores``):
its name is no method of the registry, yet its results are in the folder."""

from __future__ import annotations

from pathlib import Path

import pandas as pd
import pytest
from helpers import tiny_route_run

from gvbench_nb import cli, notebook
from gvbench_nb.reporting import execute
from gvbench_nb.runner import method_outputs

IMPORTED = "my-tool"


@pytest.fixture(scope="module")
def with_import(tmp_path_factory) -> Path:
    """orb-nn on a synthetic route of 6 frames (160x120) and IMPORTED's scores of the same pairs; the params."""
    folder = tmp_path_factory.mktemp("imported")
    path = tiny_route_run(folder, ["orb-nn"])
    table = pd.read_csv(method_outputs.method_dir(folder / "out", "orb-nn") / "pairs.csv")
    scores = folder / "scores.csv"
    table.assign(score=table["score"] * 2 + 1)[["query", "reference", "label", "score"]].to_csv(scores, index=False)
    argv = ["import-scores", str(scores), "--sequence", "tiny", "--method", IMPORTED]
    assert cli.main([*argv, "--output-dir", str(folder / "out")]) == 0
    return path


@pytest.mark.reliability
def test_an_imported_method_is_no_missing_result(with_import):
    out = with_import.parent / "out"
    assert notebook.missing_methods(out, [IMPORTED, "orb-nn"]) == []
    assert notebook.missing_methods(out, [IMPORTED, "sift-nn"]) == ["sift-nn"]
    assert notebook.require_results(with_import, [IMPORTED]) == out


@pytest.mark.slow
@pytest.mark.reliability
def test_the_explorer_and_an_analysis_notebook_show_an_imported_method(with_import, tmp_path):
    figures = tmp_path / "figures"
    parameters = {"params_file": str(with_import), "figures_dir": str(figures)}
    execute.execute_notebook("explore_pairs.ipynb", tmp_path / "explore_pairs.ipynb", parameters)
    assert list(pd.read_csv(figures / "explore_pair.csv")["method"]) == ["orb-nn", IMPORTED]
    out = with_import.parent / "out"
    checked = {"output_dirs": [str(out)], "params_files": [str(with_import)], "ensure_methods": [IMPORTED]}
    execute.execute_notebook(
        "analysis_results_table.ipynb", tmp_path / "t.ipynb", {**checked, "output_dir": str(tmp_path)}
    )
    assert IMPORTED in set(pd.read_csv(tmp_path / "results_with_paper.csv")["method"])


def test_the_explorers_table_shows_an_imported_methods_counts_as_not_measured(with_import):
    from gvbench_nb.evaluation import run_tables
    from gvbench_nb.studies import explore_pairs as explore

    tables = run_tables.load_pairs_tables(with_import.parent / "out", ["orb-nn", IMPORTED])
    view = explore.pair_across_methods(tables, 0)
    assert view["num_inliers"].iloc[0] == tables["orb-nn"]["num_inliers"].iloc[0] and pd.isna(
        view["num_inliers"].iloc[1]
    )
    html = explore.shown_table(view).to_html()
    assert not any(word in html for word in ("nan", "None", "&lt;NA&gt;")), html
