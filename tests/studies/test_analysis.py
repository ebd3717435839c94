"""The analyses read written results right: best-per-column, the paper join, failures,
offsets, normalised inliers and the query bootstrap (agreement, coverage, determinism)."""

from __future__ import annotations

import re

import numpy as np
import pandas as pd
import pytest
from sklearn.metrics import average_precision_score
from written_runs import add_run

from gvbench_nb import notebook
from gvbench_nb.evaluation import bootstrap, run_tables
from gvbench_nb.protocol import metrics
from gvbench_nb.runner import method_outputs, method_runs, scoring
from gvbench_nb.studies import failures, inlier_histograms, results_table, runtime_vs_mr


def pairs_frame(queries, references, labels, scores) -> pd.DataFrame:
    return pd.DataFrame(
        {
            "pair_index": range(len(labels)),
            "query": queries,
            "reference": references,
            "label": labels,
            "score": scores,
            "num_inliers": scores,
            "num_matches": np.asarray(scores) + 10,
        }
    )


def grouped_scores(rng: np.random.Generator, n_queries: int, per_query: int, separation: float = 1.0) -> pd.DataFrame:
    """Independent queries of ``per_query`` pairs: label ~ Bernoulli(0.4), score ~ N(separation * label, 1)."""
    n = n_queries * per_query
    labels = (rng.random(n) < 0.4).astype(int)
    labels[0], labels[1] = 1, 0  # both classes, always
    scores = rng.normal(separation * labels, 1.0)
    queries = np.repeat([f"q{i}" for i in range(n_queries)], per_query)
    return pairs_frame(queries, [f"r{i}" for i in range(n)], labels, scores)


def test_best_per_column_marks_all_ties_never_nan_and_lower_is_better_per_column():
    table = pd.DataFrame({"a": [0.5, 0.9, 0.9], "b": [np.nan, 0.1, 0.2], "c": [np.nan, np.nan, np.nan]})
    best = run_tables.best_per_column(table)
    assert best["a"].tolist() == [False, True, True]
    assert best["b"].tolist() == [False, False, True]
    assert not best["c"].any()
    table = pd.DataFrame({"max_recall": [0.2, 0.4], "seconds_per_pair": [0.3, 0.1]})
    best = run_tables.best_per_column(table, {"seconds_per_pair": False})
    assert best["max_recall"].tolist() == [False, True]
    assert best["seconds_per_pair"].tolist() == [False, True]
    assert run_tables.best_per_column(table, False)["max_recall"].tolist() == [True, False]


def test_paper_table_join_labels_values_and_mapping(tmp_path):
    path = tmp_path / "paper_table.csv"
    path.write_text(
        "method,sequence,ap,max_recall\nSIFT+NN,night,62.1,8.7\nNotOurs+XX,night,97.9,18.2\n"
        "SIFT+NN,day,98.1,36.0\nDISK+LG,night,81.4,25.0\n"
    )
    paper = results_table.load_paper_table(path)
    assert paper.loc[paper.paper_name == "SIFT+NN", "method"].unique().tolist() == ["sift-nn"]
    assert paper.loc[paper.paper_name == "NotOurs+XX", "method"].isna().all()  # not one of ours
    results = pd.DataFrame(
        {
            "method": ["sift-nn", "disk-nn"],
            "sequence": ["night", "night"],
            "profile": ["paper", "paper"],
            "ap": [0.7, 0.5],
            "max_recall": [0.1, 0.2],
        }
    )
    joined = results_table.join_paper_table(results, paper)
    assert set(joined["source"]) == {"ours", "paper"}
    theirs = joined[joined.source == "paper"]
    # Only methods and sequences we ran; % turned into fractions.
    assert theirs[["method", "sequence"]].values.tolist() == [["sift-nn", "night"]]
    assert theirs["ap"].iloc[0] == pytest.approx(0.621)
    assert theirs["max_recall"].iloc[0] == pytest.approx(0.087)
    wide = results_table.results_table(joined)
    assert ("night", "ap", "paper") in wide.columns and ("night", "ap", "ours") in wide.columns
    assert wide.loc[("sift-nn (SIFT+NN)", "paper"), ("night", "max_recall", "paper")] == pytest.approx(0.087)
    assert np.isnan(wide.loc[("disk-nn (DISK+NN)", "paper"), ("night", "ap", "paper")])
    best = run_tables.best_per_column(wide[results_table.metric_columns(wide)])
    assert best.loc[("disk-nn (DISK+NN)", "paper"), ("night", "max_recall", "ours")]
    assert results_table._percent(wide.loc[("disk-nn (DISK+NN)", "paper"), ("night", "ap", "paper")]) == "-"


def test_top_false_positives_and_negatives_with_frame_offsets():
    queries = [f"night/Image{i:03d}.jpg" for i in (10, 10, 10, 20, 20, 20)]
    references = [f"day/Image{j:03d}.jpg" for j in (10, 14, 40, 21, 23, 20)]
    table = pairs_frame(queries, references, [1, 0, 0, 1, 0, 1], [50, 30, 30, 3, 44, 0])
    false_positives = failures.top_false_positives(table, 2)
    assert false_positives["pair_index"].tolist() == [4, 1]  # 44, then the first of the tied 30s
    assert failures.top_false_negatives(table, 2)["pair_index"].tolist() == [5, 3]
    offsets = failures.ground_truth_offsets(table)
    assert offsets["frame_offset"].tolist() == [0, 4, 30, 1, 3, 0]
    failed = failures.failures_table({"m": table}, k=2)
    fp = failed[failed.kind == "false_positive"]
    assert fp["frame_offset"].tolist() == [3, 4] and fp["rank"].tolist() == [1, 2]
    near = failures.near_miss_false_positives(table, offsets, top_k=2, low=3, high=5)
    assert near["near_in_top"] == 2 and near["near_share_all_false"] == pytest.approx(2 / 3)
    # As a page shows it: no index column, offsets rounded.
    page = notebook.table(failed.assign(distance_m=27.028347), precision=1).to_html()
    assert ">27.0<" in page and "27.028" not in page and 'class="row_heading' not in page


def test_pose_offsets_from_poses_csv(tmp_path):
    rows = []
    for name, x, yaw in (("night/000.png", 0.0, 0.0), ("day/001.png", 3.0, 0.0), ("day/002.png", 0.0, 90.0)):
        c, s = np.cos(np.radians(yaw)), np.sin(np.radians(yaw))
        rotation = np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])  # optical axis turned by yaw
        rows.append(
            {
                "image": name,
                "x": x,
                "y": 4.0,
                "z": 1.5,
                **{f"r{i}{j}": rotation[i, j] for i in range(3) for j in range(3)},
            }
        )
    pd.DataFrame(rows).to_csv(tmp_path / "poses.csv", index=False)
    table = pairs_frame(["night/000.png"] * 2, ["day/001.png", "day/002.png"], [1, 0], [5, 1])
    offsets = failures.ground_truth_offsets(table, tmp_path)
    assert offsets["distance_m"].tolist() == pytest.approx([3.0, 0.0])
    assert offsets["heading_deg"].tolist() == pytest.approx([0.0, 90.0])
    assert offsets["frame_offset"].tolist() == [1, 2]
    with pytest.raises(KeyError, match="no pose"):
        failures.ground_truth_offsets(pairs_frame(["night/009.png"], ["day/001.png"], [1], [1]), tmp_path)


def test_normalised_inliers_and_overlap_summary():
    table = pairs_frame(["q"] * 6, list("abcdef"), [1, 1, 1, 0, 0, 1], [40, 10, 0, 10, 5, 0])
    assert inlier_histograms.normalised_inliers(table).tolist() == pytest.approx([1, 0.25, 0, 0.25, 0.125, 0])
    summary = inlier_histograms.inlier_overlap_summary(table)
    assert summary["true_zero_inliers"] == pytest.approx(0.5)
    assert summary["top_false_score"] == 10 and summary["top_false_normalised"] == pytest.approx(0.25)
    # Strictly above the top false pair is exactly what MR can reach.
    assert summary["true_above_top_false"] == pytest.approx(
        metrics.max_recall_at_full_precision(table["label"], table["score"])
    )
    assert inlier_histograms.normalised_inliers(table.assign(num_inliers=0)).tolist() == [0] * 6


def test_weighted_metrics_equal_sklearn_on_repeated_pairs():
    rng = np.random.default_rng(3)
    checked = 0
    for _ in range(100):
        n = int(rng.integers(4, 40))
        labels = rng.integers(0, 2, n)
        scores = rng.integers(0, 5, n).astype(float)  # many ties, as inlier counts have
        weights = rng.integers(0, 3, (4, n))
        ap, max_recall = bootstrap.weighted_ap_max_recall(labels, scores, weights)
        for row in range(4):
            repeated = np.repeat(np.arange(n), weights[row])
            lab, s = labels[repeated], scores[repeated]
            if lab.sum() in (0, len(lab)):
                continue
            assert ap[row] == pytest.approx(average_precision_score(lab, s))
            assert max_recall[row] == pytest.approx(metrics.max_recall_at_full_precision(lab, s))
            checked += 1
    assert checked > 200


def test_query_resample_weights_keep_a_query_together():
    codes = np.array([0, 0, 0, 1, 1, 2])
    weights = bootstrap.query_resample_weights(codes, 50, seed=1)
    assert weights.shape == (50, 6)
    assert (weights[:, 0] == weights[:, 1]).all() and (weights[:, 3] == weights[:, 4]).all()
    # Each resample draws exactly n_queries queries.
    assert (weights[:, [0, 3, 5]].sum(axis=1) == 3).all()


def test_bootstrap_ci_covers_the_true_ap_about_95_percent():
    rng = np.random.default_rng(2024)
    huge = grouped_scores(rng, 100_000, 4)
    true_ap = average_precision_score(huge["label"], huge["score"])
    covered, widths = 0, []
    for _ in range(100):
        sample = grouped_scores(rng, 50, 4)
        interval = bootstrap.bootstrap({"m": sample}, 200, seed=int(rng.integers(1 << 31))).intervals()
        ap = interval[interval.metric == "ap"].iloc[0]
        covered += ap["low"] <= true_ap <= ap["high"]
        widths.append(ap["high"] - ap["low"])
    # 95% nominal; 100 experiments give a binomial sd of about 2.2 points.
    assert 0.87 <= covered / 100 <= 0.995, covered
    assert 0.05 < np.mean(widths) < 0.4


def test_bootstrap_scores_all_resamples_in_one_vectorised_pass(monkeypatch):
    # What keeps 1000 resamples fast, without a clock: the metric runs once a method for all
    # resamples (plus once for the estimate), however many resamples there are.
    calls = []
    weighted = bootstrap.weighted_ap_max_recall

    def counting(labels, scores, weights):
        calls.append(weights.shape[0])
        return weighted(labels, scores, weights)

    monkeypatch.setattr(bootstrap, "weighted_ap_max_recall", counting)
    table = grouped_scores(np.random.default_rng(0), 200, 10)
    for n_resamples in (10, 1000):
        calls.clear()
        result = bootstrap.bootstrap({"a": table, "b": table.assign(score=-table["score"])}, n_resamples, seed=0)
        assert sorted(calls) == [1, 1, n_resamples, n_resamples]
        assert all(len(samples) == n_resamples for samples in result.samples.values())


def write_fake_run(output_dir, method="sift-nn", sequence="toy", profile="repository"):
    table = pairs_frame(["q0", "q0", "q1", "q1"], ["r0", "r1", "r2", "r3"], [1, 0, 1, 0], [30, 5, 3, 8])
    table = table.assign(extract_seconds=0.1, match_seconds=0.2, verify_seconds=0.05)
    run = {"sequence": sequence, "conf": {"paper_name": "SIFT+NN", "profile": profile}}
    add_run(output_dir, method, table, run, view=True)


def test_ensure_results_runs_nothing_when_pairs_exist(tmp_path, monkeypatch):
    output_dir = tmp_path / "toy"
    write_fake_run(output_dir)
    (tmp_path / "pairs.txt").write_text("q0 r0 1\n")
    params = tmp_path / "toy.yaml"
    params.write_text(
        f"sequence: toy\npairs: pairs.txt\nimage_root: .\nmethods: [sift-nn]\nprofile: repository\n"
        f"output_dir: {output_dir}\n"
    )

    def refuse(*args, **kwargs):
        raise AssertionError("run_method must not run when pairs.csv exists")

    monkeypatch.setattr(method_runs, "run_method", refuse)
    assert notebook.require_results(params, ["sift-nn"], compute_missing=True) == output_dir
    results = run_tables.load_results(run_tables.find_output_dirs(tmp_path))
    assert results["method"].tolist() == ["sift-nn"]
    assert results["max_recall"].iloc[0] == pytest.approx(0.5)
    assert results["fps"].iloc[0] == pytest.approx(1 / 0.35)
    with pytest.raises(FileNotFoundError, match="no finished run"):
        run_tables.find_output_dirs(tmp_path, ["absent"])


def test_report_summary_page_labels_paper_and_links_notebooks(tmp_path, monkeypatch):
    import argparse

    from gvbench_nb.reporting import report

    output_dir = tmp_path / "outputs" / "toy"
    write_fake_run(output_dir, profile="paper")
    scoring.evaluate(output_dir)
    from gvbench_nb.evaluation import reference_values

    toy_paper = pd.DataFrame(
        {"reference_name": ["SIFT+NN"], "method": ["sift-nn"], "sequence": ["toy"], "ap": [0.5], "max_recall": [0.125]}
    )
    monkeypatch.setattr(reference_values, "paper_table", lambda: toy_paper)
    report_dir = tmp_path / "report"
    (report_dir / "toy").mkdir(parents=True)
    (report_dir / "toy" / "analysis_failures.html").write_text("<html></html>")
    executed = [
        report.ExecutedNotebook(
            "toy", report_dir / "toy" / "analysis_failures.ipynb", report_dir / "toy" / "analysis_failures.html"
        ),
        report.ExecutedNotebook("toy", report_dir / "toy" / "analysis_uncertainty.ipynb", None, "ValueError: boom"),
    ]
    page = report.summary_page(report_dir, [output_dir], executed)
    assert ">paper<" in page and ">ours<" in page
    assert ">12.5<" in page and ">50.0<" in page  # the paper's values, in %
    assert "href='toy/analysis_failures.html'" in page
    assert "failed: ValueError: boom" in page
    assert re.search(r">\d+ \(all\)<", page)  # the row's pairs, and that no --limit cut them

    parser = argparse.ArgumentParser()
    report.add_command(parser.add_subparsers(dest="command"))
    argv = ["report", "--outputs-root", str(tmp_path / "outputs"), "--sequences", "absent"]
    args = parser.parse_args([*argv, "--output-dir", str(report_dir)])
    with pytest.raises(method_outputs.ResultsError, match="absent"):  # refused before any work
        report.run_folders(args)


def test_results_table_without_the_papers_table_shows_ours_only_and_every_rows_pairs(tmp_path):
    results = pd.DataFrame(
        {"method": ["sift-nn"], "sequence": ["sample"], "profile": ["paper"], "ap": [0.8], "max_recall": [0.1]}
    )
    paper = results_table.load_paper_table(tmp_path / "absent.csv")
    assert paper.empty
    joined = results_table.join_paper_table(results, paper)
    assert joined["source"].tolist() == [run_tables.OURS_LABEL]
    assert results_table.results_table(joined).shape == (1, 2)
    # With the published tables: how many pairs a row has, and whether --limit cut them.
    results = two_profile_results().assign(n_pairs=[240, 24, 240], limit=[None, 24, None])
    wide = results_table.results_table(results_table.join_paper_table(results, results_table.load_paper_table()))
    assert wide[("night", "pairs", "ours")].tolist() == ["240 (all)", "24 (--limit)", "240 (all)"]
    assert wide.columns[0] == ("night", "pairs", "ours")
    assert wide[("night", "ap", "ours")].map(results_table._percent).tolist() == ["60.0", "55.0", "90.0"]
    assert "24 (--limit)" in results_table.style_results_table(wide).to_html()


def two_profile_results() -> pd.DataFrame:
    """sift-nn under both profiles on one sequence, plus disk-lg under the repository's."""
    return pd.DataFrame(
        {
            "sequence": ["night", "night", "night"],
            "method": ["sift-nn", "sift-nn", "disk-lg"],
            "profile": ["paper", "repository", "repository"],
            "ap": [0.60, 0.55, 0.90],
            "max_recall": [0.08, 0.05, 0.40],
            "device": "cpu",
            "extract_seconds_per_pair": [0.1, 0.02, 0.3],
            "match_seconds_per_pair": 0.01,
            "verify_seconds_per_pair": 0.01,
            "seconds_per_pair": [0.12, 0.04, 0.32],
        }
    )


def test_results_table_keeps_one_row_a_method_and_profile():
    joined = results_table.join_paper_table(
        two_profile_results(), results_table.load_paper_table(), results_table.load_repository_table()
    )
    wide = results_table.results_table(joined)
    assert list(wide.index) == [
        ("sift-nn (SIFT+NN)", "paper"),
        ("sift-nn (SIFT+NN)", "repository"),
        ("disk-lg (DISK+LG)", "repository"),
    ]
    assert wide.loc[("sift-nn (SIFT+NN)", "paper"), ("night", "ap", "ours")] == pytest.approx(0.60)
    assert wide.loc[("sift-nn (SIFT+NN)", "repository"), ("night", "ap", "ours")] == pytest.approx(0.55)
    # Published values only beside the same protocol: the paper's 62.1 % in the paper row,
    # the repository's 0.6136 in the repository row, never the other way round.
    assert wide.loc[("sift-nn (SIFT+NN)", "paper"), ("night", "ap", "paper")] == pytest.approx(0.621)
    assert np.isnan(wide.loc[("sift-nn (SIFT+NN)", "paper"), ("night", "ap", run_tables.REPOSITORY_LABEL)])
    assert wide.loc[("sift-nn (SIFT+NN)", "repository"), ("night", "ap", run_tables.REPOSITORY_LABEL)] == pytest.approx(
        0.6136
    )
    assert np.isnan(wide.loc[("sift-nn (SIFT+NN)", "repository"), ("night", "ap", "paper")])
    assert np.isnan(wide.loc[("disk-lg (DISK+LG)", "repository"), ("night", "ap", "paper")])
    assert set(joined["label"]) == {
        "sift-nn (paper profile)",
        "sift-nn (repository profile)",
        "disk-lg (repository profile)",
        "sift-nn (paper)",
        f"sift-nn ({run_tables.REPOSITORY_LABEL})",
        f"disk-lg ({run_tables.REPOSITORY_LABEL})",
    }


def test_the_same_run_twice_in_one_table_is_an_error():
    results = pd.concat([two_profile_results(), two_profile_results().iloc[[1]]], ignore_index=True)
    results["output_dir"] = ["a", "a", "a", "b"]
    with pytest.raises(ValueError, match=r"night/repository/sift-nn in a; night/repository/sift-nn in b"):
        results_table.join_paper_table(results, results_table.load_paper_table())


def test_results_without_profile_say_what_to_do():
    with pytest.raises(ValueError, match="no profile column"):
        results_table.join_paper_table(two_profile_results().drop(columns="profile"), results_table.load_paper_table())


def test_radar_and_bars_label_every_line_with_its_profile():
    import matplotlib

    matplotlib.use("Agg")
    from gvbench_nb.studies import results_table

    results = pd.concat(
        [two_profile_results().assign(sequence=s) for s in ("day", "night", "season")], ignore_index=True
    )
    joined = results_table.join_paper_table(
        results, results_table.load_paper_table(), results_table.load_repository_table()
    )
    labels = results_table.max_recall_radar(joined).axes[0].get_legend_handles_labels()[1]
    assert "sift-nn (paper profile)" in labels and "sift-nn (repository profile)" in labels
    assert "sift-nn (paper)" in labels and f"sift-nn ({run_tables.REPOSITORY_LABEL})" in labels
    assert not any(label.endswith("(ours)") for label in labels)
    bars = results_table.max_recall_radar(joined[joined.sequence == "night"])
    ticks = [t.get_text() for t in bars.axes[0].get_yticklabels()]
    assert ticks[:2] == ["sift-nn (paper profile)", "sift-nn (repository profile)"]
    # In %, as the tables are, and the title names only what is drawn.
    assert bars.axes[0].patches[0].get_width() == pytest.approx(8.0) and "(%)" in bars.axes[0].get_xlabel()
    assert "hatched: published" in bars.texts[0].get_text()
    ours = results_table.max_recall_radar(joined[(joined.sequence == "night") & (joined.source == "ours")])
    assert ours.texts[0].get_text() == "max recall at 100% precision (%)"
    radar = results_table.max_recall_radar(joined).axes[0]
    assert radar.get_title() == "max recall at 100% precision (%)" and radar.get_ylim()[1] > 40


def test_runtime_figures_and_histograms_name_the_profile():
    import matplotlib

    matplotlib.use("Agg")

    runtime = runtime_vs_mr.runtime_table(two_profile_results())
    stacked = runtime_vs_mr.seconds_per_pair_stacked(runtime)
    assert [t.get_text() for t in stacked.axes[0].get_yticklabels()] == [
        "sift-nn (paper profile)",
        "sift-nn (repository profile)",
        "disk-lg (repository profile)",
    ]
    scatter = runtime_vs_mr.fps_vs_max_recall(runtime)
    assert {t.get_text() for t in scatter.axes[0].texts} >= {"sift-nn (paper profile)", "sift-nn (repository profile)"}
    # The log axis reads: at least three labelled ticks inside it, whatever the speeds.
    for seconds in ([0.05, 0.06, 0.08], [0.01, 1.0, 30.0]):
        figure = runtime_vs_mr.fps_vs_max_recall(runtime.assign(fps=[1 / s for s in seconds]))
        figure.canvas.draw()
        axis = figure.axes[0]
        low, high = axis.get_xlim()
        shown = [t.get_text() for t in axis.get_xticklabels() if low <= t.get_position()[0] <= high]
        assert len([t for t in shown if t]) >= 3, shown
    table = pairs_frame(["q0", "q0", "q1", "q1"], ["r0", "r1", "r2", "r3"], [1, 0, 1, 0], [30, 5, 3, 8])
    tables = {"sift-nn": table.assign(profile="paper"), "orb-nn": table.assign(profile="repository")}
    figure = inlier_histograms.normalised_inlier_histograms(tables)
    assert [a.get_title() for a in figure.axes[:2]] == ["sift-nn (paper profile)", "orb-nn (repository profile)"]
    with pytest.raises(ValueError, match="mixes profiles"):
        inlier_histograms.normalised_inlier_histograms({"sift-nn": pd.concat(tables.values())})


def test_reference_tables_ship_with_the_package_and_map_names():
    paper = results_table.load_paper_table()
    assert paper.set_index(["paper_name", "sequence"]).loc[("SIFT+NN", "day"), "ap"] == pytest.approx(0.981)
    assert paper.loc[paper.paper_name == "Doppelgangers", "method"].isna().all()
    repository = results_table.load_repository_table()
    by_name = repository.drop_duplicates("paper_name").set_index("paper_name")["method"]
    assert by_name["superpoint-lg"] == "sp-lg" and by_name["xfeat"] == "xfeat-nn" and by_name["disk-lg"] == "disk-lg"
    assert pd.isna(by_name["master"]) and pd.isna(by_name["sift-lg"])
    night = repository.set_index(["paper_name", "sequence"])
    assert night.loc[("disk-lg", "night"), "ap"] == pytest.approx(0.9661)  # fractions, as published
    assert night.loc[("sift-nn", "day"), "max_recall"] == pytest.approx(0.3534)
