"""The doors besides ``run`` (a stage notebook on its own, shards, merges, the explorer's figures) each add a
run of their own and change no earlier one, or are refused before work; same photographs and in-process
notebooks as test_run_record.py."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import matplotlib.pyplot as plt
import pandas as pd
import pytest
import test_run_record
from helpers import (
    FLIPPED,
    PAIRS,
    PAIRS8,
    added_one_run,
    check_runs_whole,
    not_in_table,
    one_sentence,
    params_file,
    run_cli,
    run_ids,
    runs_files,
    shown,
    snapshot,
    verify_on_its_own,
    write_root,
)

from gvbench_nb import run_and_publish
from gvbench_nb.data.sequences import write_pairs
from gvbench_nb.evaluation import plots
from gvbench_nb.runner import config, method_outputs

pytestmark = pytest.mark.reliability
notebooks_here = test_run_record.notebooks_here  # the fixture


def test_a_shard_and_a_merge_add_runs_and_change_no_earlier_run(tmp_path, root, capsys, notebooks_here):
    from gvbench_nb.runner import runs

    out, path = tmp_path / "out", params_file(tmp_path)
    assert run_cli(capsys, "run", str(path))[0] == 0
    first, table = run_ids(out)[0], (out / "results.csv").read_bytes()
    before = runs_files(out)
    assert run_cli(capsys, "run", str(path), "--shard", "0/2")[0] == 0
    shard = added_one_run(out, before, "shard")
    # A shard's run holds its manifest only (which shard, what it computed), which no view shows.
    assert sorted(p.name for p in (out / "runs" / shard).iterdir()) == ["manifest.json"]
    assert (out / "results.csv").read_bytes() == table and runs.current(out).entries["orb-nn"].run.name == first
    # Another run writing the folder meanwhile (its run being built) is in no one's way.
    other = runs.start(out, "run")
    (other / "orb-nn").mkdir()
    (other / "orb-nn" / "pairs.csv").write_text("half of a table")
    for door, argv in (("shard", ["--shard", "1/2"]), ("merge", ["--merge"])):
        before = runs_files(out)
        assert run_cli(capsys, "run", str(path), *argv)[0] == 0
        added_one_run(out, before, door)
    merged = run_ids(out)[-1]
    assert runs.current(out).entries["orb-nn"].run.name == merged and shown(out) == {"orb-nn": ("repository", 4)}
    assert (other / "orb-nn" / "pairs.csv").read_text() == "half of a table"
    assert check_runs_whole(out) == run_ids(out)
    first_table = pd.read_csv(out / "runs" / first / "orb-nn" / "pairs.csv")
    merged_table = pd.read_csv(out / "runs" / merged / "orb-nn" / "pairs.csv")
    assert merged_table["score"].tolist() == first_table["score"].tolist()  # the same work, shared by the stores


def test_a_merge_on_other_labels_shows_its_run_and_names_what_it_left_out(tmp_path, root, capsys, notebooks_here):
    out = tmp_path / "out"
    assert run_cli(capsys, "run", str(params_file(tmp_path)))[0] == 0
    first = run_ids(out)[0]
    flipped = params_file(tmp_path, "flipped.yaml", FLIPPED, methods=["sift-opencv-nn"])
    assert run_cli(capsys, "run", str(flipped), "--shard", "0/1")[0] == 0
    before = runs_files(out)
    code, text, err = run_cli(capsys, "run", str(flipped), "--merge")
    merged = added_one_run(out, before, "merge")
    assert code == 0 and shown(out) == {"sift-opencv-nn": ("repository", 4)} and "sift-opencv-nn" in text
    line = f"orb-nn: its latest run {first} scored 4 other pairs or labels (results {out} --run {first})"
    assert not_in_table(err) == [f"not in this table: {line}"]
    assert method_outputs.method_dir(out, "sift-opencv-nn") == out / "runs" / merged / "sift-opencv-nn"
    # On the folder's first pairs and labels, a merge's results.csv lists every method of the folder on them.
    sift = params_file(tmp_path, "sift.yaml", PAIRS, methods=["sift-opencv-nn"])
    assert run_cli(capsys, "run", str(sift), "--shard", "0/1")[0] == 0
    code, _, err = run_cli(capsys, "run", str(sift), "--merge")
    assert code == 0 and shown(out) == {"orb-nn": ("repository", 4), "sift-opencv-nn": ("repository", 4)}
    assert not_in_table(err) == []


def test_a_rerun_keeps_the_figures_the_explorer_saved(tmp_path, root, capsys, notebooks_here):
    path = params_file(tmp_path)
    assert run_cli(capsys, "run", str(path))[0] == 0
    figure = plt.figure()
    saved = plots.save(figure, tmp_path / "out" / "explore" / "explore_pair_0.png")
    plt.close(figure)
    content = saved.read_bytes()
    assert run_cli(capsys, "run", str(path))[0] == 0
    assert saved.read_bytes() == content
    figure = plt.figure()  # saved again, it replaces its own earlier file
    plots.save(figure, saved)
    plt.close(figure)
    assert run_cli(capsys, "results", str(tmp_path / "out"))[0] == 0


def test_a_notebook_run_on_its_own_that_fails_keeps_the_finished_results(tmp_path, root, capsys, notebooks_here):
    out, path = tmp_path / "out", params_file(tmp_path)
    assert run_cli(capsys, "run", str(path))[0] == 0
    before, image = snapshot(out), (root / "query" / "b.png").read_bytes()
    (root / "query" / "b.png").unlink()
    with pytest.raises(Exception, match="b.png"):
        verify_on_its_own(path, "sift-opencv-nn")
    (root / "query" / "b.png").write_bytes(image)
    after = snapshot(out)
    assert {k: v for k, v in after.items() if not k.startswith("runs/.building-")} == before  # it added nothing
    code, text, _ = run_cli(capsys, "results", str(out), "--run", run_ids(out)[0])
    assert code == 0 and "orb-nn" in text and "sift-opencv-nn" not in text and len(run_ids(out)) == 1


def test_a_limit_notebook_adds_a_run_and_removes_nothing(tmp_path, capsys, notebooks_here):
    """``papermill notebooks/02_verify.ipynb x.ipynb -p params_file p.yaml -p method orb-nn -p limit 4`` in
    a finished folder of two methods on eight pairs."""
    write_root(tmp_path / "images", ("astronaut", "coffee", "chelsea", "rocket"))
    out, path = tmp_path / "out", params_file(tmp_path, "p.yaml", PAIRS8, methods=["orb-nn", "sift-opencv-nn"])
    assert run_cli(capsys, "run", str(path))[0] == 0
    figure = plt.figure()
    plots.save(figure, out / "explore" / "explore_pair_0.png")  # a figure the explorer saved
    plt.close(figure)
    before = snapshot(out)
    assert "explore/explore_pair_0.png" in before and any(n.endswith("02_verify_orb-nn.ipynb") for n in before)
    env = {**os.environ, "PYTHONPATH": str(config.PROJECT_ROOT)}
    notebook = ["notebooks/02_verify.ipynb", str(tmp_path / "x.ipynb"), "-p", "params_file", str(path)]
    said = subprocess.run(
        [sys.executable, "-m", "papermill", *notebook, "-p", "method", "orb-nn", "-p", "limit", "4"],
        cwd=config.PROJECT_ROOT, env=env, capture_output=True, text=True, timeout=600,
    )  # fmt: skip
    assert said.returncode == 0, said.stderr[-3000:]
    after = snapshot(out)
    assert {name: after.get(name) for name in before if name != "results.csv"} == {
        name: data for name, data in before.items() if name != "results.csv"
    }  # every earlier run, notebook and figure, byte for byte
    finished, added = check_runs_whole(out)
    assert "-02_verify-" in added and len(pd.read_csv(out / "runs" / added / "orb-nn" / "pairs.csv")) == 4
    code, text, err = run_cli(capsys, "results", str(out))
    assert code == 0 and shown(out) == {"orb-nn": ("repository", 4)} and "sift-opencv-nn" not in text
    assert not_in_table(err) == [
        f"not in this table: sift-opencv-nn: its latest run {finished} scored 8 other pairs or labels "
        f"(results {out} --run {finished})"
    ]


def test_a_method_registered_from_code_is_refused_by_run_before_any_folder(tmp_path, root, capsys, monkeypatch):
    from test_extending import isolate_recipes

    from gvbench_nb import methods

    isolate_recipes(monkeypatch)
    methods.register_method("orb-mine", {"repository": methods.resolve_method("orb-nn", "repository")})
    code, _, err = run_cli(capsys, "run", str(params_file(tmp_path, methods=["orb-mine"])))
    assert code == 2 and "method orb-mine was registered from code" in one_sentence(err)
    assert not (tmp_path / "out").exists() and not (tmp_path / "cache").exists()


def test_labels_edited_while_a_run_computes_are_the_ones_its_record_binds(
    tmp_path, root, capsys, monkeypatch, notebooks_here
):
    path = params_file(tmp_path)

    def edit_labels_then_run(name: str, output_path: Path, parameters: dict) -> None:
        if name == "01_sequence.ipynb":  # after `run` read the pair file, before any method scored it
            write_pairs(tmp_path / "params-pairs.txt", FLIPPED)
        test_run_record.in_process_notebooks(name, output_path, parameters)

    monkeypatch.setattr(run_and_publish, "execute_notebook", edit_labels_then_run)
    assert run_cli(capsys, "run", str(path))[0] == 0
    table = pd.read_csv(method_outputs.method_dir(tmp_path / "out", "orb-nn") / "pairs.csv")
    assert table["label"].tolist() == [p.label for p in FLIPPED]
    # The run binds the labels its results scored: a run of another method on the same file joins them.
    monkeypatch.setattr(run_and_publish, "execute_notebook", test_run_record.in_process_notebooks)
    assert run_cli(capsys, "run", str(path), "--methods", "sift-opencv-nn")[0] == 0
    code, out, _ = run_cli(capsys, "results", str(tmp_path / "out"))
    assert code == 0 and "orb-nn" in out and "sift-opencv-nn" in out
