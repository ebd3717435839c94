"""notebooks/explore_pairs and ``explore``: the pair it shows, each method's score and rank, from
cached results only; its controls redraw every view; the command opens a working copy."""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from helpers import tiny_route_run
from written_runs import add_run

from gvbench_nb import cli, explore_lab
from gvbench_nb.evaluation import plots, run_tables
from gvbench_nb.runner import method_outputs, runs
from gvbench_nb.studies import explore_pairs as explore

NOTEBOOKS = Path(__file__).resolve().parents[2] / "notebooks"
METHODS = ["sift-nn", "orb-nn"]


def expected_rank(table: pd.DataFrame, index: int) -> int:
    """1 + the pairs scoring strictly higher: the rank as the notebook defines it."""
    return int(1 + (table["score"] > table["score"].iloc[index]).sum())


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory) -> Path:
    """sift-nn and orb-nn on the synthetic route, 6 frames of 160x120 (36 pairs, 4 false)."""
    return tiny_route_run(tmp_path_factory.mktemp("explore"), METHODS)


def test_choose_pair_by_index_and_by_a_methods_failures_and_a_tie_shares_the_best_rank():
    assert list(explore.score_ranks(pd.DataFrame({"score": [5, 9, 5, 0, 9]}))) == [3, 1, 3, 5, 1]
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
    tables = {m: pd.read_csv(method_outputs.method_dir(out, m) / "pairs.csv") for m in METHODS}
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
    # One file a view, whichever pair: the folder holds the pair shown, not one file a pair viewed.
    assert sorted(p.name for p in figures.iterdir()) == sorted(explore.FIGURE_FILES.values())
    # Under papermill the controls cell draws no widgets and says so.
    last = json.loads(executed.read_text())["cells"][-1]
    assert "controls: none" in "".join("".join(o.get("text", "")) for o in last["outputs"])


def test_matches_canvas_has_a_white_gap_between_the_two_images():
    image0 = np.zeros((4, 5, 3), np.uint8)
    image1 = np.full((6, 3, 3), 7, np.uint8)
    canvas, offset = plots.match_canvas(image0, image1, gap=2)
    assert canvas.shape == (6, 5 + 2 + 3, 3) and offset == 7
    assert (canvas[:, 5:7] == 255).all()  # the gap
    assert (canvas[:4, :5] == 0).all() and (canvas[:, 7:] == 7).all()


def test_score_histograms_of_four_methods_share_one_legend_in_a_grid():
    rng = np.random.default_rng(0)
    tables = {f"m{i}": pd.DataFrame({"label": [1, 0] * 20, "score": rng.integers(0, 50, 40)}) for i in range(4)}
    view = pd.DataFrame({"method": list(tables), "score": [t["score"].iloc[0] for t in tables.values()]})
    view = view.assign(rank=1, n_pairs=40)
    figure = plots.score_histograms(tables, view)
    visible = [axis for axis in figure.axes if axis.get_visible()]
    assert len(visible) == 4
    columns = {round(axis.get_position().x0, 2) for axis in visible}
    assert columns == {round(axis.get_position().x0, 2) for axis in visible[:2]}  # two columns
    assert all(axis.get_legend() is None for axis in visible) and len(figure.legends) == 1
    assert [t.get_text() for t in figure.legends[0].get_texts()] == ["true pairs", "false pairs", "this pair"]


@pytest.fixture
def widgets():
    """ipywidgets, whose widgets are closed after the test: one left to the interpreter's exit prints a traceback."""
    ipywidgets = pytest.importorskip("ipywidgets")
    yield ipywidgets
    ipywidgets.Widget.close_all()


@pytest.mark.parametrize("pick", explore.PICKS)
def test_controls_redraw_every_view_and_the_index_box_follows_the_pick(tiny_run, tmp_path, pick, widgets):
    out = tiny_run.parent / "out"
    tables = run_tables.load_pairs_tables(out)
    drawn: list[tuple[int, list[str]]] = []

    def draw(index, shown):
        drawn.append((index, shown))
        return explore.pair_views(out, {m: tables[m] for m in shown}, index, tmp_path)

    controls = explore.ExploreControls(tables, draw, pick="index", pair_index=3)
    controls.redraw()
    for method in METHODS:
        controls.pick_method.value = method
        controls.pick.value = pick  # no change when it is already 'index': set the index instead
        if pick == "index":
            controls.pair_index.value = 5
        expected = explore.choose_pair(tables, pick, 5, method, 1)
        assert drawn[-1] == (expected, METHODS)
        assert controls.pair_index.value == expected
        assert set(controls.drawn) == set(explore.VIEWS)
        assert list(controls.drawn["table"]["pair_index"]) == [expected] * len(METHODS)
        for name in ("matches", "scores"):
            assert controls.drawn[name].data[:8] == b"\x89PNG\r\n\x1a\n"
        controls.pick.value = "index"
    # Fewer methods shown: every view redrawn for those only.
    controls.methods.value = ("orb-nn",)
    assert drawn[-1][1] == ["orb-nn"] and list(controls.drawn["table"]["method"]) == ["orb-nn"]
    # Typing an index while a pick is chosen switches the pick to 'index'.
    controls.pick.value = "false_negative"
    controls.pick_method.value = "orb-nn"
    controls.pair_index.value = 2
    assert controls.pick.value == "index" and drawn[-1][0] == 2


def test_controls_say_what_they_do_and_leave_no_stale_view_under_a_message(tiny_run, tmp_path, widgets):
    out = tiny_run.parent / "out"
    tables = run_tables.load_pairs_tables(out)
    status_while_drawing: list[str] = []

    def draw(index, shown):
        status_while_drawing.append(controls.status.value)
        return explore.pair_views(out, {m: tables[m] for m in shown}, index, tmp_path)

    controls = explore.ExploreControls(tables, draw, pick="index", pair_index=3)
    controls.redraw()
    assert status_while_drawing[-1].startswith("drawing pair 3") and controls.status.value.startswith("pair 3:")
    assert controls.pick_method.style.description_width == "initial"  # the label whole, not 'pick_met...'
    # An index out of range is said and kept, not clamped to the last pair; no earlier view stays.
    controls.pair_index.value = 9999
    assert controls.pair_index.value == 9999 and controls.drawn == {}
    assert "0 to" in controls.status.value and "9999" in controls.status.value
    # pick_method offers the methods shown; none selected means all, and the status says so.
    controls.pair_index.value = 1
    controls.methods.value = (METHODS[-1],)
    assert controls.pick_method.options == (METHODS[-1],) and controls.pick_method.value == METHODS[-1]
    controls.methods.value = ()
    assert list(controls.drawn["table"]["method"]) == METHODS and "(none selected: all shown)" in controls.status.value
    assert controls.pick_method.options == tuple(METHODS)
    # A rank beyond the method's pairs: said, the views cleared.
    controls.pick.value = "false_positive"
    controls.pick_rank.value = 99_999
    assert "fewer than pick_rank 99999" in controls.status.value and controls.drawn == {}


def test_explore_writes_a_working_copy_pointed_at_the_run_showing_every_method_and_keeps_it(tiny_run):
    out = tiny_run.parent / "out"
    source = NOTEBOOKS / "explore_pairs.ipynb"
    before = source.read_bytes()
    (out / "explore" / "explore_pairs.ipynb").unlink(missing_ok=True)  # another test's copy
    copy, written = explore_lab.prepare_copy(out)
    assert written and copy == out / "explore" / "explore_pairs.ipynb"
    notebook = json.loads(copy.read_text())
    parameters = next(c for c in notebook["cells"] if "parameters" in c["metadata"].get("tags", []))
    namespace: dict = {}
    exec("".join(parameters["source"]), namespace)
    assert namespace["params_file"] == str(runs.resolved_params(out)) and namespace["output_dir"] == str(out)
    assert namespace["methods"] is None and "jupytext" not in notebook["metadata"]
    assert explore.default_methods(tiny_run) == METHODS  # None: every method the run holds
    copy.write_text(copy.read_text().replace("Explore one pair", "My notes"))
    edited = copy.read_bytes()
    assert explore_lab.prepare_copy(out) == (copy, False) and copy.read_bytes() == edited
    assert source.read_bytes() == before
    command = explore_lab.lab_command(copy, 9999, "t", open_browser=False)
    assert f"--ServerApp.root_dir={copy.parent}" in command and command[-1] == str(copy)


def test_explore_command_opens_lab_on_the_copy(tiny_run, monkeypatch, capsys):
    out = tiny_run.parent / "out"
    started = []
    monkeypatch.setattr(explore_lab.os, "execve", lambda path, argv, env: started.append((argv, env)))
    assert cli.main(["explore", str(out), "--no-browser", "--port", "9876"]) == 0
    printed = capsys.readouterr().out
    assert str(out / "explore" / "explore_pairs.ipynb") in printed
    assert "http://127.0.0.1:9876/lab/tree/explore_pairs.ipynb?token=" in printed
    argv, env = started[0]
    assert "--ServerApp.open_browser=False" in argv and "--ServerApp.port=9876" in argv
    # Its JupyterLab reads the package's page config too (no news pop-up), besides the user's.
    assert env["JUPYTER_CONFIG_PATH"].split(os.pathsep)[0] == str(explore_lab.LAB_CONFIG)
    assert (explore_lab.LAB_CONFIG / "labconfig" / "page_config.json").is_file()


@pytest.mark.parametrize("folder", ["missing", "no_record", "no_results"])
def test_explore_refuses_a_folder_that_is_no_finished_run_in_one_sentence(tmp_path, capsys, folder):
    target = tmp_path / "out"
    if folder != "missing":
        target.mkdir()
    if folder == "no_results":
        (target / "params.resolved.yaml").write_text("sequence: x\n")
    assert cli.main(["explore", str(target)]) == 2
    error = capsys.readouterr().err
    assert error.startswith("error: ") and error.count("\n") == 1 and "Traceback" not in error
    assert not (target / "explore").exists()


def test_the_recorded_cache_is_found_without_cache_dir(tmp_path):
    out = tmp_path / "outputs" / "seq"
    out.mkdir(parents=True)
    assert run_tables.resolve_cache_dir(out) == tmp_path / "cache"  # no run: the default ($GVBENCH_CACHE)
    table = pd.DataFrame({"pair_index": [0, 1], "query": ["q", "q"], "reference": ["r0", "r1"], "label": [1, 0]})
    params = f"sequence: seq\ncache_dir: {tmp_path / 'elsewhere'}\n"
    add_run(out, "sift-nn", table.assign(score=[2, 1]), files={"params.resolved.yaml": params})
    assert run_tables.resolve_cache_dir(out) == tmp_path / "elsewhere"
    assert run_tables.resolve_cache_dir(out, tmp_path / "given") == tmp_path / "given"


def test_explore_refuses_a_busy_port_before_writing_anything(tiny_run, capsys):
    import socket

    out = tiny_run.parent / "out"
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = busy.getsockname()[1]
        copy = out / "explore" / "explore_pairs.ipynb"
        copy.unlink(missing_ok=True)
        assert cli.main(["explore", str(out), "--port", str(port)]) == 2
    error = capsys.readouterr().err
    assert error == f"error: port {port} is in use on 127.0.0.1; give another --port or leave it out\n"
    assert not copy.exists()
