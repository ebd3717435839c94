"""The paper's items: Table II counts a list and keeps the paper's text apart, Table III's Average
and 1st / 2nd / 3rd places, on hand-made tables with the answers worked out by hand."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from gvbench_nb.studies import paper


def test_places_rank_each_column_ties_sharing_a_place():
    table = pd.DataFrame({"a": [0.9, 0.5, 0.9, 0.1, 0.3], "b": [0.2, np.nan, 0.4, 0.6, 0.8]})
    # a: 0.9 (twice) 1st, 0.5 2nd, 0.3 3rd, 0.1 unplaced; b: 0.8, 0.6, 0.4, then 0.2 and NaN unplaced.
    assert paper.places(table)["a"].tolist() == [1, 2, 1, 0, 3]
    assert paper.places(table)["b"].tolist() == [0, 0, 3, 2, 1]


def results_rows() -> pd.DataFrame:
    rows = [
        ("day", "sift-nn", 0.8, 0.2),
        ("night", "sift-nn", 0.6, 0.0),
        ("day", "orb-nn", 0.9, 0.1),
        ("night", "orb-nn", 0.4, 0.3),
        ("day", "xfeat-nn", 0.7, 0.5),  # no night run: no average
    ]
    return pd.DataFrame(rows, columns=["sequence", "method", "ap", "max_recall"]).assign(profile="repository")


def test_table_iii_averages_over_the_sequences_and_marks_places():
    table = paper.table_iii(results_rows())
    average = table[("Average", "ap")]
    assert average.iloc[0] == pytest.approx(0.7) and average.iloc[1] == pytest.approx(0.65)
    assert np.isnan(average.iloc[2])
    assert table[("Average", "max_recall")].iloc[:2].tolist() == pytest.approx([0.1, 0.2])
    html = paper.style_table_iii(table).to_html()
    assert "Average" in html and "font-weight: bold" in html and "underline" in html and "italic" in html


def test_table_ii_counts_the_list_beside_the_papers_text(tmp_path):
    # A list of 3 queries: q0 with 2 candidates (1 true), q1 with 2 (0 true), q2 with 1 (1 true).
    (tmp_path / "nordland.txt").write_text(
        "s1/q0.jpg s2/r0.jpg 1\ns1/q0.jpg s2/r1.jpg 0\ns1/q1.jpg s2/r2.jpg 0\ns1/q1.jpg s2/r3.jpg 0\ns1/q2.jpg s2/r4.jpg 1\n"
    )
    summary = paper.sequence_summary([], tmp_path).set_index(["sequence", "source"])
    counted = summary.loc[("nordland", paper.COUNTED)]
    assert (counted.traverse, counted.queries, counted.pairs, counted.positives) == ("s1 vs s2", 3, 5, 2)
    assert counted.candidates == "1-2"
    text = summary.loc[("nordland", paper.PAPER_TEXT)]
    assert (text.queries, text.pairs) == (1415, 28300) and counted.condition == text.condition == "seasonal"
    assert ("uacampus", paper.COUNTED) not in summary.index  # no list there: only the paper's text
    assert summary.loc[("uacampus", paper.PAPER_TEXT), "candidates"] == 10
    assert paper.summary_text(summary.reset_index()).iloc[0]["pairs"] == "5"
