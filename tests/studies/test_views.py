"""The report's and the analysis notebooks' views read as one paper: an imported method named the
same way everywhere and said absent where its data are, AP and MR in % under worded headers, no
synthetic route averaged with recorded sequences, radar gaps left open, the published tables in
one sequence order, readable transfer heatmaps, caption sizes read per traversal."""

from __future__ import annotations

import matplotlib
import numpy as np
import pandas as pd
import pytest
from PIL import Image
from written_runs import add_run

from gvbench_nb.evaluation import plots, run_tables
from gvbench_nb.reporting import tables
from gvbench_nb.runner import scoring
from gvbench_nb.studies import deployment, inlier_histograms, paper, results_table, runtime_vs_mr

matplotlib.use("Agg")

pytestmark = pytest.mark.reliability


def results_rows(sequences: dict[str, bool]) -> pd.DataFrame:
    """sift-nn and an imported my-tool on each sequence (True: a synthetic route)."""
    rows = [
        {"sequence": s, "method": m, "profile": p, "paper_name": n, "ap": 0.5, "max_recall": 0.25, "synthetic": syn}
        for s, syn in sequences.items()
        for m, p, n in (("sift-nn", "repository", "SIFT+NN"), ("my-tool", "imported", "my-tool (imported)"))
    ]
    seconds = {c: [0.01, np.nan] * len(sequences) for c in run_tables.TIME_COLUMNS}
    return pd.DataFrame(rows).assign(
        n_pairs=240, device="cpu", seconds_per_pair=[0.03, np.nan] * len(sequences), **seconds
    )


def test_an_imported_method_is_labelled_imported_in_every_table_and_figure():
    results = results_rows({"night": False})
    assert plots.run_label("my-tool", "imported") == "my-tool (imported)"
    assert plots.run_label("sift-nn", "repository") == "sift-nn (repository profile)"
    wide = results_table.results_table(results_table.join_paper_table(results, pd.DataFrame()))
    assert wide.index.get_level_values("method").tolist() == ["sift-nn (SIFT+NN)", "my-tool (imported)"]
    assert paper.table_iii(results).index.get_level_values("method")[1] == "my-tool (imported)"
    intervals = pd.DataFrame({"method": ["my-tool"], "metric": ["ap"], "estimate": [0.5]})
    shown = run_tables.readable_table(intervals, ["estimate"], run_tables.run_labels(results))
    assert shown.iloc[0].tolist() == ["my-tool (imported)", "AP", 50.0]
    # A run missing a sequence: '-' in each of its cells there, its pairs too.
    two = pd.concat([results, results_rows({"day": False}).iloc[:1]], ignore_index=True)
    html = results_table.style_results_table(results_table.results_table(results_table.join_paper_table(two, None)))
    assert ">nan<" not in html.to_html()
    joined = results_table.join_paper_table(results.assign(sequence="night"), pd.DataFrame())
    legend = results_table.max_recall_radar(joined).axes[0].get_yticklabels()
    assert "my-tool (imported)" in [t.get_text() for t in legend]


def test_an_imported_method_is_said_absent_in_one_line_where_its_data_are():
    results = results_rows({"night": False})
    assert runtime_vs_mr.runtime_table(results)["method"].tolist() == ["sift-nn"]
    assert runtime_vs_mr.unmeasured_lines(results) == [
        "my-tool (imported), on night: no seconds were measured here (scores imported); not in the runtime views"
    ]
    table = pd.DataFrame({"label": [1, 0, 1, 0], "score": [9.0, 1, 5, 2], "num_inliers": [9, 1, 5, 2]})
    runs = {
        "sift-nn": table.assign(profile="repository"),
        "my-tool": table.assign(num_inliers=np.nan, profile="imported"),
    }
    counted, lines = inlier_histograms.with_inlier_counts(runs)
    assert list(counted) == ["sift-nn"]
    assert lines == ["my-tool (imported): its scores come without inlier counts; no panel"]
    # The score ranks its pairs all the same: its overlap row is there.
    assert inlier_histograms.inlier_overlap_table(runs)["true_above_top_false"].tolist() == [1.0, 1.0]
    # `results` and `run`: its seconds column says imported, never nan.
    seconds = tables.compact_table(
        results.assign(
            timers=["this run", "imported"],
            **{f"{m}_{end}": 0.1 for m in run_tables.METRICS for end in ("low", "high")},
        )
    )["s/pair"]
    assert seconds.tolist() == ["0.030", "imported"]
    assert scoring.timers_source({"imported": {"file": "x"}, "this_run": {}}) == "imported"


def test_run_prints_imported_for_an_imported_methods_seconds(tmp_path, capsys):
    from gvbench_nb import run_and_publish

    results = results_rows({"night": False}).assign(n_positives=90, timers=["this run", "imported"])
    run_and_publish.print_results(results, ["sift-nn", "my-tool"])
    printed = capsys.readouterr()
    row = next(line for line in printed.out.splitlines() if line.strip().startswith("my-tool"))
    assert row.split()[-2:] == ["imported", "imported"] and "nan" not in row
    assert "from the cache" not in printed.out + printed.err


def test_headers_are_words_and_ap_and_mr_are_in_percent():
    frame = pd.DataFrame(
        {"method": ["sift-nn"], "ap": [0.5], "max_recall": [0.25], "n_valid": [1000], "true_above_top_false": [0.25]}
    )
    shown = run_tables.readable_table(frame, ["true_above_top_false"])
    assert not [c for c in shown.columns if "_" in c or c in ("ap", "max_recall")]
    assert shown.iloc[0].tolist() == ["sift-nn", 50.0, 25.0, 1000, 25.0]
    assert {"AP (%)", "MR (%)"} <= set(shown.columns)
    html = paper.style_table_iii(paper.table_iii(results_rows({"night": False, "day": False}))).to_html()
    assert "AP (%)" in html and "MR (%)" in html and ">ap<" not in html and ">50.0<" in html
    styled = results_table.style_results_table(
        results_table.results_table(results_table.join_paper_table(results_rows({"night": False}), pd.DataFrame()))
    ).to_html()
    assert "MR (%)" in styled and ">max_recall<" not in styled
    figure = paper.method_across_sequences(results_rows({"night": False}))
    assert [a.get_ylabel() for a in figure.axes] == ["MR (%)", "AP (%)"] and figure.axes[0].get_ylim()[1] > 100
    assert figure.axes[0].patches[0].get_height() == pytest.approx(25.0)
    scatter = runtime_vs_mr.fps_vs_max_recall(runtime_vs_mr.runtime_table(results_rows({"night": False})))
    assert scatter.axes[0].collections[0].get_offsets()[0][1] == pytest.approx(25.0)
    assert "%" not in "".join(t.get_text() for t in scatter.axes[0].get_yticklabels())


def test_an_average_spans_two_or_more_recorded_sequences_never_a_synthetic_route():
    mixed = results_rows({"gardens_point": False, "viewpoint": False, "sample": True})
    real, synthetic = paper.real_and_synthetic(mixed)
    assert set(real["sequence"]) == {"gardens_point", "viewpoint"} and set(synthetic["sequence"]) == {"sample"}
    table = paper.table_iii(real)
    assert "sample" not in table.columns.get_level_values("sequence")
    assert table[(paper.AVERAGE, "ap")].tolist() == [0.5, 0.5]
    one = paper.table_iii(results_rows({"gardens_point": False}))
    assert paper.AVERAGE not in one.columns.get_level_values("sequence")
    assert paper.AVERAGE not in paper.table_iii(synthetic, average=False).columns.get_level_values("sequence")


def test_load_results_marks_a_folder_of_a_rendered_route_synthetic(tmp_path):
    table = pd.DataFrame(
        {"pair_index": range(4), "query": ["q0", "q0", "q1", "q1"], "reference": ["r0", "r1", "r2", "r3"]}
    ).assign(label=[1, 0, 1, 0], score=[9, 2, 7, 3], extract_seconds=0.1, match_seconds=0.1, verify_seconds=0.1)
    for name, rendered in (("route", True), ("recorded", False)):
        images = tmp_path / f"{name}_images"
        images.mkdir()
        if rendered:
            (images / "generator.json").write_text("{}")
        add_run(tmp_path / name, "sift-nn", table, {"sequence": name, "image_root": str(images), "pairs": {}})
        imported = {"image_root": "", "pairs": {}, "imported": {"file": "scores.csv"}}  # read no images
        add_run(tmp_path / name, "my-tool", table, imported | {"sequence": name, "conf": {"profile": "imported"}})
    loaded = run_tables.load_results([tmp_path / "route", tmp_path / "recorded"])
    assert set(loaded["method"]) == {"sift-nn", "my-tool"}
    assert loaded.groupby("sequence")["synthetic"].all().to_dict() == {"recorded": False, "route": True}


def test_a_radar_never_draws_a_line_across_a_missing_vertex():
    def rows(sequences: list[str]) -> pd.DataFrame:
        return pd.DataFrame(
            [
                {"method": m, "profile": "repository", "sequence": s, "source": run_tables.OURS_LABEL}
                | {"max_recall": 0.3}
                for m in ("sift-nn", "xfeat-nn")
                for s in sequences
                if (m, s) != ("xfeat-nn", "viewpoint")
            ]
        )

    figure = results_table.max_recall_radar(rows(["day", "night", "viewpoint", "season", "uacampus"]))
    axis = figure.axes[0]
    # The radar spans the sequences every line has, each line a closed ring over all of them.
    assert [t.get_text() for t in axis.get_xticklabels()] == ["day", "night", "season", "uacampus"]
    for line in axis.get_lines():
        assert np.isfinite(line.get_ydata()).all() and len(line.get_xdata()) == 5, line.get_label()
        assert np.allclose(np.diff(line.get_xdata()), np.pi / 2), line.get_label()
    assert "viewpoint" in figure.texts[-1].get_text()
    # Three sequences, one missing for a method: bars of every value, no radar.
    bars = results_table.max_recall_radar(rows(["gardens_point", "viewpoint", "sample"]))
    assert all(axis.name != "polar" for axis in bars.axes) and len(bars.axes) == 3


def test_the_published_tables_list_their_sequences_in_one_order():
    order = list(dict.fromkeys(results_table.load_paper_table()["sequence"]))
    repository = list(dict.fromkeys(results_table.load_repository_table()["sequence"]))
    assert repository == [s for s in order if s in repository]
    assert order[-2:] == ["nordland", "uacampus"]
    for source in (run_tables.PAPER_LABEL, run_tables.REPOSITORY_LABEL):
        ticks = [t.get_text() for t in paper.published_radar(source).axes[0].get_xticklabels()]
        assert ticks == [s for s in order if s in ticks]


def test_transfer_heatmaps_keep_their_text_readable_at_any_size():
    def transfer(methods: int, sequences: int) -> pd.DataFrame:
        names = [f"s{i}" for i in range(sequences)]
        return pd.DataFrame(
            [
                {"method": f"m{m}", "profile": "imported" if m == 0 else "paper", "calibration": c, "target": t}
                | {"recall": 0.5, "false_loops": 0}
                for m in range(methods)
                for c in names
                for t in names
            ]
        )

    for methods, sequences in ((4, 1), (1, 1), (2, 6)):
        figure = deployment.transfer_figure(transfer(methods, sequences))
        figure.canvas.draw()
        panels = [a for a in figure.axes if a.get_visible() and a.images]
        # At most three panels a row (a page scales a wide figure down, and its text with it), and
        # each cell at least about an inch, its text at 9 pt.
        assert len(panels) == methods and len({round(a.get_position().x0, 3) for a in panels}) <= 3
        for axis in panels:
            box = axis.get_window_extent().transformed(figure.dpi_scale_trans.inverted())
            assert box.width / sequences >= 0.9 and box.height / sequences >= 0.9
            assert {t.get_fontsize() for t in axis.texts} == {9}
        assert panels[0].get_title() == "m0 (imported)"


def test_a_runtime_caption_gives_each_traversals_own_image_size(tmp_path):
    images = tmp_path / "images"
    for folder, size in (("night", (640, 360)), ("day_right", (960, 540))):
        (images / folder).mkdir(parents=True)
        Image.new("RGB", size).save(images / folder / "0.png")
    output = tmp_path / "out"
    pairs = pd.DataFrame(
        {"query": ["night/0.png"], "reference": ["day_right/0.png"], "label": [1], "score": [3.0], "num_inliers": [3]}
    )
    extractor = {"name": "sift", "type": "opencv_sift", "resize_to": [512, 288]}
    run = {
        "image_root": str(images),
        "conf": {"extractor": extractor, "matcher": {"name": "nn"}, "profile": "repository"},
        "environment": {"device": "cpu", "device_name": "x", "cpu_count": 2},
    }
    add_run(output, "sift-nn", pairs, run)
    caption = runtime_vs_mr.run_description(output, ["sift-nn"], tmp_path / "cache")
    assert "sift: night 640x360, day_right 960x540; resized to 512x288" in caption
