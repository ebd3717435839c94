"""``python -m gvbench_nb report``: a header explaining only the table's columns, PR curves of every
method and profile, notebook pages without code, and a run's own cache found from its record."""

from __future__ import annotations

import argparse
import re
from pathlib import Path

import pandas as pd
import pytest
from written_runs import add_run

from gvbench_nb import cli
from gvbench_nb.evaluation import plots
from gvbench_nb.reporting import report
from gvbench_nb.studies import results_table


def wide_table(paper: pd.DataFrame, profile: str = "paper") -> pd.DataFrame:
    results = pd.DataFrame(
        {"method": ["sift-nn"], "sequence": ["toy"], "profile": [profile], "ap": [0.8], "max_recall": [0.1]}
    )
    return results_table.results_table(results_table.join_paper_table(results, paper, pd.DataFrame()))


def test_table_note_explains_only_the_columns_the_table_has():
    published = pd.DataFrame(
        {"paper_name": ["SIFT+NN"], "method": ["sift-nn"], "sequence": ["toy"], "ap": [0.5], "max_recall": [0.1]}
    )
    with_paper = report.table_note(wide_table(published), paper_found=True)
    assert "GV-Bench paper's published values" in with_paper and "GV-Bench repository" not in with_paper
    # The paper's table has other sequences only: the table has our columns alone.
    elsewhere = report.table_note(wide_table(published.assign(sequence="other")), paper_found=True)
    assert "published values" not in elsewhere.replace("No published values", "")
    assert "No published values exist" in elsewhere
    assert "was not found" in report.table_note(wide_table(published.iloc[:0]), paper_found=False)


def test_pr_curves_name_every_method_and_profile_and_keep_a_methods_colour():
    tables = {
        (method, profile): pd.DataFrame({"label": [1, 0, 1, 0], "score": scores})
        for method, profile, scores in (
            ("sift-nn", "repository", [9, 1, 5, 2]),
            ("sift-nn", "paper", [9, 6, 5, 2]),
            ("orb-nn", "repository", [3, 1, 2, 4]),
        )
    }
    figure = plots.pr_curves_by_profile(tables, title="toy")
    texts = [t.get_text() for t in figure.axes[0].get_legend().get_texts()]
    assert texts == [
        "sift-nn (repository profile): AP 100.0%, MR 100.0%",
        "sift-nn (paper profile): AP 83.3%, MR 50.0%",
        "orb-nn (repository profile): AP 58.3%, MR 0.0%",
    ]
    lines = [line for line in figure.axes[0].get_lines() if line.get_label() in texts]
    assert lines[0].get_color() == lines[1].get_color() != lines[2].get_color()
    assert [line.get_linestyle() for line in lines] == ["-", "--", "-"]


@pytest.mark.slow
def test_report_on_a_run_with_its_own_cache_dir_hides_code_and_shows_pr_curves(tmp_path):
    """A run whose cache_dir is not the default: every analysis notebook finds the cache from the
    run's record; the pages show no code; the summary shows the sequence's PR curves."""
    cache = tmp_path / "elsewhere" / "features_cache"
    params = tmp_path / "sample.yaml"
    params.write_text(
        f"sequence: sample\npairs_builder: sample\nbuilder_options: {{}}\nimage_root: {tmp_path / 'data'}\n"
        f"pairs: {tmp_path / 'data' / 'pairs.txt'}\nmethods: [sift-nn, orb-nn]\nprofile: repository\n"
        f"output_dir: {tmp_path / 'outputs' / 'sample'}\ncache_dir: {cache}\nseed: 0\n"
    )
    assert cli.main(["run", str(params), "--limit", "24"]) == 0
    assert (cache / "features").is_dir() and not (tmp_path / "outputs" / "cache").exists()
    report_dir = tmp_path / "report"
    code = cli.main(["report", "--outputs-root", str(tmp_path / "outputs"), "--output-dir", str(report_dir)])
    index = (report_dir / "index.html").read_text()
    assert "failed:" not in index and code == 0
    assert "src='pr_curves_sample.png'" in index and (report_dir / "pr_curves_sample.png").is_file()
    pages = sorted(report_dir.rglob("*.html"))
    # index, the table, the sequence's, the paper's and deployment's
    assert len(pages) == 2 + len(report.PER_SEQUENCE_NOTEBOOKS) + len(report.PAPER_NOTEBOOKS)
    for page in pages:
        if page.name != "index.html":
            text = page.read_text()
            # Elements, not the stylesheet's rules: no code editor (markdown stays), outputs present.
            assert not re.search(r'class="[^"]*\bjp-InputArea-editor\b', text), page
            assert re.search(r'class="[^"]*\bjp-OutputArea\b', text), page
            assert not re.search(r"\bimport gvbench_nb|from gvbench_nb", text), page
    # analysis_failures drew the top failures' matches from the run's own cache.
    failures = Path(report_dir / "sample" / "analysis_failures.ipynb").read_text()
    assert "KeyError" not in failures


def test_report_takes_run_folders_or_a_run_folder_as_outputs_root(tmp_path, capsys):
    """``report OUTPUT_DIR...`` reads those run folders; ``--outputs-root`` may be a run folder
    itself or hold them; a folder showing no finished run is one sentence, before any work."""
    outputs = tmp_path / "outputs"
    for name in ("a", "b"):
        add_run(
            outputs / name, "sift-nn", pd.DataFrame({"query": ["q"], "reference": ["r"], "label": [1], "score": [1]})
        )
    (outputs / "empty").mkdir()
    parser = argparse.ArgumentParser()
    report.add_command(parser.add_subparsers(dest="command"))

    def folders(*words: str) -> list[Path]:
        return report.run_folders(parser.parse_args(["report", *words]))

    assert folders(str(outputs / "b"), str(outputs / "a")) == [outputs / "b", outputs / "a"]
    assert folders("--outputs-root", str(outputs / "a")) == [outputs / "a"]
    assert folders("--outputs-root", str(outputs)) == [outputs / "a", outputs / "b"]
    assert cli.main(["report", str(outputs / "empty"), "--output-dir", str(tmp_path / "report")]) == 2
    error = capsys.readouterr().err
    assert error.count("\n") == 1 and f"{outputs / 'empty'} shows no finished run" in error
    assert not (tmp_path / "report").exists()
    # Two run folders of one name get a report sub-folder each.
    assert report.page_folders([tmp_path / "x" / "sample", tmp_path / "y" / "sample"]) == {
        tmp_path / "x" / "sample": "x-sample",
        tmp_path / "y" / "sample": "y-sample",
    }
