"""The doors besides ``run`` (shards, merges, the explorer's figures) write results as ``run`` does
or are refused before work; same photographs and in-process notebooks as test_run_record.py."""

from __future__ import annotations

import os
import threading
import time
from pathlib import Path

import matplotlib.pyplot as plt
import pandas as pd
import pytest
import test_run_record
from test_run_record import FLIPPED, PAIRS, hold_lock, one_sentence, params_file, run_cli, snapshot

from gvbench_nb import run_and_publish
from gvbench_nb.data.sequences import write_pairs
from gvbench_nb.evaluation import plots
from gvbench_nb.runner import config, method_runs, record, scoring, sequence_build

pytestmark = pytest.mark.reliability
root, notebooks_here = test_run_record.root, test_run_record.notebooks_here  # the fixtures


def published(folder: Path) -> dict[str, bytes]:
    """The folder's results as a reader sees them: the unit files and derived tables."""
    return {k: v for k, v in snapshot(folder).items() if k.endswith((".csv", "run.json", ".png"))}


def test_a_shard_or_merge_on_other_labels_into_a_folder_of_other_methods_is_refused(
    tmp_path, root, capsys, notebooks_here
):
    assert run_cli(capsys, "run", str(params_file(tmp_path)))[0] == 0
    before = published(tmp_path / "out")
    flipped = params_file(tmp_path, "flipped.yaml", FLIPPED, methods=["sift-opencv-nn"])
    for option in (["--shard", "0/1"], ["--merge"]):
        code, _, err = run_cli(capsys, "run", str(flipped), *option)
        assert code == 2 and "holds results of orb-nn computed on other pairs, labels or images" in one_sentence(err)
        assert published(tmp_path / "out") == before
    assert not (tmp_path / "out" / "sift-opencv-nn" / "pairs.csv").exists()
    # On the folder's own pairs and labels, a merge's results.csv lists every method of the folder.
    sift = params_file(tmp_path, "sift.yaml", PAIRS, methods=["sift-opencv-nn"])
    assert run_cli(capsys, "run", str(sift), "--shard", "0/1")[0] == 0
    assert run_cli(capsys, "run", str(sift), "--merge")[0] == 0
    assert sorted(pd.read_csv(tmp_path / "out" / "results.csv")["method"]) == ["orb-nn", "sift-opencv-nn"]


def test_a_merge_while_a_run_holds_the_folder_is_refused_and_a_shard_never_changes_a_result(
    tmp_path, root, capsys, notebooks_here
):
    path = params_file(tmp_path)
    assert run_cli(capsys, "run", str(path))[0] == 0
    before = published(tmp_path / "out")
    holder = hold_lock(tmp_path / "out")
    try:
        # A shard fills only the caches (keyed by content), which any number of writers share.
        assert run_cli(capsys, "run", str(path), "--shard", "0/1")[0] == 0
        code, _, err = run_cli(capsys, "run", str(path), "--merge")
        assert code == 2 and f"another run is writing {tmp_path / 'out'} (pid {holder.pid}" in one_sentence(err)
        assert published(tmp_path / "out") == before
    finally:
        holder.kill()
        holder.wait()
    assert run_cli(capsys, "run", str(path), "--shard", "0/2")[0] == 0  # not held: the same
    assert published(tmp_path / "out") == before
    code, out, _ = run_cli(capsys, "results", str(tmp_path / "out"))
    assert code == 0 and "orb-nn" in out


def test_a_rerun_keeps_the_figures_the_explorer_saved(tmp_path, root, capsys, notebooks_here):
    path = params_file(tmp_path)
    assert run_cli(capsys, "run", str(path))[0] == 0
    figure = plt.figure()
    saved = plots.save(figure, tmp_path / "out" / "explore" / "explore_pair_0.png")
    plt.close(figure)
    content = saved.read_bytes()
    assert run_cli(capsys, "run", str(path))[0] == 0
    assert saved.read_bytes() == content
    # Saved again, it replaces its own earlier file (the package wrote it).
    figure = plt.figure()
    plots.save(figure, saved)
    plt.close(figure)
    assert "explore/explore_pair_0.png" in record.read_record(tmp_path / "out")["files"]


def verify_on_its_own(path: Path, method: str = "orb-nn", **overrides) -> None:
    """What ``02_verify`` does when papermill, JupyterLab or nbmake runs it on its own."""
    params = config.load_params(path, **overrides)
    method_runs.run_method_of_params(params, sequence_build.prepare_sequence(params), method, progress=False)


def test_a_notebook_run_on_its_own_that_fails_keeps_the_finished_results(tmp_path, root, capsys, notebooks_here):
    path = params_file(tmp_path)
    assert run_cli(capsys, "run", str(path))[0] == 0
    before = published(tmp_path / "out")
    run_record = (tmp_path / "out" / record.RECORD_NAME).read_bytes()
    (root / "query" / "b.png").unlink()
    with pytest.raises(Exception, match="b.png"):
        verify_on_its_own(path)
    assert published(tmp_path / "out") == before
    assert (tmp_path / "out" / record.RECORD_NAME).read_bytes() == run_record
    assert not list((tmp_path / "out").rglob(".unfinished.json"))


def test_a_notebook_run_on_its_own_on_fewer_pairs_leaves_no_figure_of_the_earlier_run(
    tmp_path, root, capsys, notebooks_here
):
    path = params_file(tmp_path)
    assert run_cli(capsys, "run", str(path))[0] == 0
    out = tmp_path / "out"
    # On the folder's own inputs, a new method's results join the folder; the run's notebooks still show it.
    verify_on_its_own(path, "sift-opencv-nn")
    assert (out / "02_verify_orb-nn.ipynb").is_file() and not (out / "results.csv").exists()
    code, text, _ = run_cli(capsys, "results", str(out))
    assert code == 0 and "orb-nn" in text and "sift-opencv-nn" in text
    # On fewer pairs, what the run derived from the four-pair results is gone, and nothing else.
    figure = plt.figure()
    explored = plots.save(figure, out / "explore" / "explore_pair_0.png")
    plt.close(figure)
    verify_on_its_own(path, limit=2)
    assert len(pd.read_csv(out / "orb-nn" / "pairs.csv")) == 2
    left = sorted(p.relative_to(out).as_posix() for p in out.rglob("*") if p.is_file())
    assert not [name for name in left if name.endswith((".ipynb", ".yaml")) or name == "results.csv"], left
    assert explored.is_file() and (out / "sift-opencv-nn" / "pairs.csv").is_file()
    # The folder now mixes two pair lists: its readers refuse it, naming the methods.
    code, _, err = run_cli(capsys, "results", str(out))
    assert code == 2 and "orb-nn" in one_sentence(err) and "sift-opencv-nn" in err


def test_a_publication_that_cannot_finish_says_so_and_no_reader_shows_the_mix(
    tmp_path, root, capsys, notebooks_here, monkeypatch
):
    both = {"methods": ["orb-nn", "sift-opencv-nn"]}
    assert run_cli(capsys, "run", str(params_file(tmp_path, **both)))[0] == 0
    flipped = params_file(tmp_path, "flipped.yaml", FLIPPED, **both)
    replace = os.replace

    def immutable_run_json(source, target):  # as `chattr +i` on one published file would
        if ".run-" in str(source) and ".run-" not in str(target) and str(target).endswith("orb-nn/run.json"):
            raise PermissionError(1, "Operation not permitted", str(target))
        replace(source, target)

    monkeypatch.setattr(os, "replace", immutable_run_json)
    code, _, err = run_cli(capsys, "run", str(flipped))
    assert code == 2 and "stopped while publishing" in err and "previous run's results" not in err
    for command in (["results"], ["compare"]):  # the move still cannot finish
        code, out, err = run_cli(capsys, *command, str(tmp_path / "out"))
        assert code == 2 and out == "" and "a run stopped while publishing" in one_sentence(err)
    monkeypatch.setattr(os, "replace", replace)
    assert run_cli(capsys, "results", str(tmp_path / "out"))[0] == 0  # now the reader finishes it
    assert pd.read_csv(tmp_path / "out" / "orb-nn" / "pairs.csv")["label"].tolist() == [p.label for p in FLIPPED]


def test_a_method_registered_from_code_is_refused_by_run_before_any_folder(tmp_path, root, capsys, monkeypatch):
    from test_extending import isolate_recipes

    from gvbench_nb import methods

    isolate_recipes(monkeypatch)
    methods.register_method("orb-mine", {"repository": methods.resolve_method("orb-nn", "repository")})
    code, _, err = run_cli(capsys, "run", str(params_file(tmp_path, methods=["orb-mine"])))
    assert code == 2 and "method orb-mine was registered from code" in one_sentence(err)
    assert not (tmp_path / "out").exists() and not (tmp_path / "cache").exists()


def test_a_reader_polling_while_a_run_publishes_sees_each_run_whole(tmp_path, root, capsys, monkeypatch):
    both = {"methods": ["orb-nn", "sift-opencv-nn"]}
    assert run_cli(capsys, "run", str(params_file(tmp_path, **both)))[0] == 0
    out = tmp_path / "out"

    def read() -> dict[str, list[float]]:
        return {m: scoring.load_pairs_table(out, m)["score"].tolist() for m in scoring.readable_methods(out)}

    first = read()
    second = {m: [score + 1 for score in scores] for m, scores in first.items()}
    # The next publication, as a run makes it: its stage holds every method, each file moved
    # in place 0.1 s after the last, so readers land mid-move.
    published = record.read_record(out)
    stage = record.open_stage(out)
    for name in published["published"]:
        (stage / name).parent.mkdir(parents=True, exist_ok=True)
        (stage / name).write_bytes((out / name).read_bytes())
    for method in first:
        table = pd.read_csv(stage / method / "pairs.csv")
        table["score"] += 1
        table.to_csv(stage / method / "pairs.csv", index=False)
    bindings = {m: {k: v for k, v in b.items() if k != "files"} for m, b in published["methods"].items()}
    replace = os.replace

    def slow_replace(source, target):
        if threading.current_thread().name == "publisher":
            time.sleep(0.1)
        replace(source, target)

    monkeypatch.setattr(os, "replace", slow_replace)

    def publish() -> None:
        with record.FolderLock(out):
            record.publish(out, stage, bindings)

    publisher = threading.Thread(target=publish, name="publisher")
    polls = [record.read_whole(out, read)]
    publisher.start()
    while publisher.is_alive():
        polls.append(record.read_whole(out, read))  # raises on a refusal
    publisher.join()
    polls.append(record.read_whole(out, read))
    assert polls[0] == first and polls[-1] == second
    assert all(poll in (first, second) for poll in polls), "a poll showed half of two runs"
    assert len(polls) > 3


def test_labels_edited_while_a_run_computes_are_the_ones_its_record_binds(tmp_path, root, capsys, monkeypatch):
    path = params_file(tmp_path)

    def edit_labels_then_run(name: str, output_path: Path, parameters: dict) -> None:
        if name == "01_sequence.ipynb":  # after `run` read the pair file, before any method scored it
            write_pairs(tmp_path / "params-pairs.txt", FLIPPED)
        test_run_record.in_process_notebooks(name, output_path, parameters)

    monkeypatch.setattr(run_and_publish, "execute_notebook", edit_labels_then_run)
    assert run_cli(capsys, "run", str(path))[0] == 0
    assert pd.read_csv(tmp_path / "out" / "orb-nn" / "pairs.csv")["label"].tolist() == [p.label for p in FLIPPED]
    # The record binds the labels the results scored: a run of another method on the same file joins them.
    monkeypatch.setattr(run_and_publish, "execute_notebook", test_run_record.in_process_notebooks)
    assert run_cli(capsys, "run", str(path), "--methods", "sift-opencv-nn")[0] == 0
    code, out, _ = run_cli(capsys, "results", str(tmp_path / "out"))
    assert code == 0 and "orb-nn" in out and "sift-opencv-nn" in out
