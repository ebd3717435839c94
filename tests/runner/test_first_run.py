"""A first run: its first lines say what it runs, with which feature cache and, when long, how long;
the cache stays put whatever the output folder; what it prints reads cleanly."""

from __future__ import annotations

import contextlib
import io
import json
import logging
import sys
from pathlib import Path

import cv2
import pandas as pd
import pytest
from helpers import in_process_notebooks, params_file, run_cli

from gvbench_nb import cli, notebook, run_and_publish
from gvbench_nb.data.sequences import Pair, Sequence
from gvbench_nb.io_utils import progress_bar
from gvbench_nb.runner import config, image_features, method_outputs, runs, sequence_build

pytestmark = pytest.mark.reliability
PROJECT = Path(__file__).resolve().parents[2]


@pytest.fixture
def notebooks_here(monkeypatch):
    monkeypatch.setattr(run_and_publish, "execute_notebook", in_process_notebooks)


def extracted(output_dir: Path, method: str = "orb-nn") -> int:
    run = json.loads((method_outputs.method_dir(output_dir, method) / "run.json").read_text())
    return run["this_run"]["extraction"]["extracted"]


# ------------------------------------------------------------ the cache --
def test_the_default_cache_is_named_first_and_stays_put_whatever_the_output_folder(
    tmp_path, root, capsys, notebooks_here
):
    path = params_file(tmp_path, cache_dir=None)
    cache = tmp_path / "cache"  # $GVBENCH_CACHE of this test (conftest.own_feature_cache)
    first, second = tmp_path / "one" / "out", tmp_path / "two" / "out"
    code, out, err = run_cli(capsys, "run", str(path), "--output-dir", str(first))
    assert code == 0, err
    assert out.splitlines()[0].endswith(f"-> {first} (feature cache {cache})")
    code, out, err = run_cli(capsys, "run", str(path), "--output-dir", str(second))
    assert code == 0, err
    assert extracted(first) == 4 and extracted(second) == 0  # the second folder's run found every image cached
    assert not (tmp_path / "one" / "cache").exists() and not (tmp_path / "two" / "cache").exists()
    # A params file's own cache_dir wins; $GVBENCH_CACHE moves the default.
    mine = params_file(tmp_path, name="mine.yaml", cache_dir=str(tmp_path / "mine"))
    assert config.load_params(mine)["cache_dir"] == str(tmp_path / "mine")
    assert Path(config.load_params(path)["cache_dir"]) == cache


# ------------------------------------------------------------ the estimate --
def test_a_run_estimated_over_ten_minutes_says_so_with_its_estimate_before_any_work(
    tmp_path, root, capsys, notebooks_here, monkeypatch
):
    photo = cv2.imread(str(root / "query" / "a.png"))
    for frame in range(40):  # 40 queries of their own contents, each against both references
        photo[0, 0] = frame
        cv2.imwrite(str(root / "query" / f"{frame}.png"), photo)
    pairs = [Pair(f"query/{frame}.png", f"reference/{r}.png", int(r == "a")) for frame in range(40) for r in "ab"]
    path = params_file(tmp_path, pairs=pairs, methods=["disk-nn", "disk-lg"])
    monkeypatch.setattr(runs, "start", lambda *args: pytest.fail("the note comes before the run's folder is made"))
    with pytest.raises(pytest.fail.Exception):
        run_cli(capsys, "run", str(path))
    said = capsys.readouterr()
    # DISK's measured 3.88 s an image x 42 images, counted once for both methods; disk-lg's 10.4 s a pair x 80 pairs.
    assert said.out.splitlines()[0].startswith("photos: 80 pairs, 42 images, methods disk-nn, disk-lg")
    assert said.err.splitlines()[0] == (
        "note: this run is estimated at 17 minutes (disk-nn 3 minutes, disk-lg 14 minutes) from costs measured "
        "on a 2-core CPU; --methods or --limit N makes it shorter"
    )


def test_the_params_files_default_methods_are_estimated_within_minutes(shared_data, tmp_path):
    from gvbench_nb.runner import run_estimate

    for name in ("gardens_point", "gardens_point_viewpoint", "gardens_point_night_viewpoint", "sample"):
        params = config.load_params(PROJECT / "params" / f"{name}.yaml", output_dir=str(tmp_path / name))
        sequence = sequence_build.prepare_sequence(params)
        counted: set[str] = set()
        seconds = 0.0
        for method in params["methods"]:
            conf = run_estimate.method_registry.resolve_method(method, params["profile"])
            estimate = run_estimate.method_seconds(sequence, conf, tmp_path / "cache", 0, counted)
            assert estimate is not None, f"{name}: no measured cost for {method}"
            seconds += estimate
        assert (run_estimate.long_run_note(params, sequence) is None) == (seconds <= run_estimate.LONG_RUN_SECONDS)


# ------------------------------------------------------------ what a run prints --
def test_the_results_table_follows_the_methods_asked_with_three_decimals(tmp_path, root, capsys, notebooks_here):
    code, out, err = run_cli(capsys, "run", str(params_file(tmp_path, methods=["sift-nn", "orb-nn"])))
    assert code == 0, err
    lines = out.splitlines()
    header = next(i for i, line in enumerate(lines) if line.split()[:2] == ["method", "profile"])
    rows = [line.split() for line in lines[header + 1 : header + 3]]
    assert [row[0] for row in rows] == ["sift-nn", "orb-nn"]  # as asked, not as results.csv holds them
    assert all(len(value.split(".")[1]) == 3 for row in rows for value in row[4:7]), lines[header : header + 3]


def test_status_lines_and_progress_bars_each_start_their_own_line():
    log = logging.getLogger("gvbench_nb.test")
    both = io.StringIO()  # a log file holding stdout and stderr
    with contextlib.redirect_stdout(both), contextlib.redirect_stderr(both):
        bar = progress_bar(total=3, desc="extract orb", file=sys.stderr, mininterval=0)
        bar.update()
        log.info("executing 02_verify.ipynb")
        bar.update(2)
        bar.close()
    lines = both.getvalue().split("\n")
    assert "executing 02_verify.ipynb" in lines and not [line for line in lines if "\r" in line], lines

    class Terminal(io.StringIO):
        def isatty(self) -> bool:
            return True

    terminal = Terminal()
    with contextlib.redirect_stdout(terminal), contextlib.redirect_stderr(terminal):
        bar = progress_bar(total=3, desc="extract orb", file=sys.stderr, mininterval=0)
        bar.update()
        log.info("executing 02_verify.ipynb")
        bar.close()
    before = terminal.getvalue().split("executing 02_verify.ipynb")[0]
    assert before.split("\n")[-1].split("\r")[-1] == ""  # the bar's line was cleared and the cursor sent back


def test_data_fetch_quiet_prints_nothing_when_every_file_is_there(tmp_path, capsys, monkeypatch):
    from gvbench_nb.data import fetch

    monkeypatch.setattr(fetch, "fetch", lambda names, **options: dict.fromkeys(names, 0))
    assert cli.main(["data", "fetch", "gvbench-lists", "--to", str(tmp_path), "--quiet"]) == 0
    said = capsys.readouterr()
    assert said.out == "" and said.err == f"data folder: {tmp_path.resolve()}\n"


def test_the_header_counts_images_and_their_distinct_contents(tmp_path, root, capsys, notebooks_here):
    (root / "reference" / "c.png").write_bytes((root / "query" / "a.png").read_bytes())  # byte-identical
    pairs = [Pair("query/a.png", "reference/a.png", 1), Pair("query/b.png", "reference/b.png", 1)]
    pairs.append(Pair("query/b.png", "reference/c.png", 0))
    code, out, err = run_cli(capsys, "run", str(params_file(tmp_path, pairs=pairs)))
    assert code == 0, err
    assert out.splitlines()[0].startswith("photos: 3 pairs, 5 images, 4 distinct contents, methods orb-nn")
    assert len(image_features.content_keys(Sequence("photos", root, pairs))) == 4


def test_the_verify_notebook_prints_whole_numbers_as_integers():
    table = pd.DataFrame({"label": [0, 0, 1], "num_matches": [10, 20, 31], "num_inliers": [1, 2, 30]})
    quartiles = notebook.quartiles_by_label(table)
    text = quartiles.to_string()
    assert quartiles.loc[("num_matches", "count"), 0] == 2 and " 2.000000" not in text
    assert quartiles.loc[("num_matches", "mean"), 1] == 31 and quartiles.loc[("num_inliers", "std"), 0] == 0.7
    assert "notebook.quartiles_by_label(table)" in (PROJECT / "notebooks" / "02_verify.py").read_text()


def test_the_explorer_table_hides_pandas_row_numbers():
    from gvbench_nb.studies import explore_pairs

    view = pd.DataFrame({"method": ["sift-nn", "orb-nn"], "num_inliers": [3, 4]})
    html = explore_pairs.shown_table(view).to_html()
    assert "sift-nn" in html and "row_heading" not in html  # no 0, 1 before the methods
    assert 'display(explore.shown_table(views["table"]))' in (PROJECT / "notebooks" / "explore_pairs.py").read_text()


def test_tests_never_use_the_per_user_cache():
    import tempfile

    from gvbench_nb.data import fetch

    assert fetch.cache_dir().is_relative_to(Path(tempfile.gettempdir()).resolve())  # conftest's, for this session
