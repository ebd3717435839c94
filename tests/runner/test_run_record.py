"""An output folder is its runs, each written once: every door adds ``runs/<id>/`` and no process changes
an earlier run; the folder's table is derived from the runs by one rule. Runs go through ``cli.main``
with the notebooks computed in this process (``in_process_notebooks``), on small photographs matched with
ORB; docs/reliability.md lists each test beside its promise. (Other test files import the helpers' names
FLIPPED, PAIRS, in_process_notebooks, one_sentence, params_file, run_cli and snapshot from here.)"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import helpers
import pandas as pd
import pytest
import yaml
from helpers import (
    FLIPPED,
    PAIRS,
    check_runs_whole,
    in_process_notebooks,
    one_sentence,
    params_file,
    run_cli,
    run_ids,
    runs_files,
    snapshot,
)

from gvbench_nb import cli, run_and_publish
from gvbench_nb.data.sequences import Pair, Sequence, write_pairs
from gvbench_nb.evaluation import run_tables
from gvbench_nb.protocol.metrics import evaluate_scores
from gvbench_nb.reporting import tables
from gvbench_nb.runner import config, method_outputs, method_runs, scoring, sequence_build

pytestmark = pytest.mark.reliability


@pytest.fixture
def notebooks_here(monkeypatch):
    monkeypatch.setattr(run_and_publish, "execute_notebook", in_process_notebooks)
    monkeypatch.setattr(run_and_publish, "kernels_ahead", lambda count: contextlib.nullcontext())  # none is used


# ---------------------------------------------------------------- ownership --
@pytest.mark.parametrize("output_dir", ["out", ""])  # "": the params file's folder
def test_a_folder_of_the_users_files_is_refused_and_left_byte_identical(
    tmp_path, root, capsys, notebooks_here, output_dir
):
    out = tmp_path / output_dir
    (out / "orb-nn").mkdir(parents=True, exist_ok=True)
    for name in ("results.csv", "orb-nn/pairs.csv", "pr_curves.png", "01_sequence.ipynb"):
        (out / name).write_text(f"the user's own {name}\n")
    path = params_file(tmp_path, output_dir=str(out) if output_dir else "")
    before = snapshot(out)
    code, _, err = run_cli(capsys, "run", str(path))
    assert code == 2
    assert f"output folder {out} is not empty" in one_sentence(err) and "runs/" in err
    assert snapshot(out) == before


def earlier_layout(tmp_path: Path, capsys) -> Path:
    """A folder as an earlier gvbench-nb left it: ``gvbench-run.json`` and each method's files at its top."""
    assert run_cli(capsys, "run", str(params_file(tmp_path, output_dir=str(tmp_path / "new"))))[0] == 0
    run = tmp_path / "new" / "runs" / run_ids(tmp_path / "new")[0]
    old = tmp_path / "old"
    (old / "orb-nn").mkdir(parents=True)
    for name in ("results.csv", "01_sequence.ipynb", "params.resolved.yaml"):
        shutil.copy(run / name, old / name)
    shutil.copy(run / "orb-nn" / "pairs.csv", old / "orb-nn" / "pairs.csv")
    record = json.loads((run / "orb-nn" / "run.json").read_text())
    record.pop("cache_dir")  # which that layout's run.json did not name
    (old / "orb-nn" / "run.json").write_text(json.dumps({**record, "run_id": "20261201T120000Z-1234-ab12cd"}))
    (old / "gvbench-run.json").write_text(json.dumps({"package": "gvbench-nb", "state": "published"}))
    return old


def test_a_folder_of_the_earlier_layout_is_refused_naming_upgrade_and_upgrade_takes_it_in(
    tmp_path, root, capsys, notebooks_here
):
    old = earlier_layout(tmp_path, capsys)
    before = snapshot(old)
    upgrade = f"python -m gvbench_nb upgrade {old}"
    for argv in (["run", str(params_file(tmp_path, output_dir=str(old)))], ["results", str(old)]):
        code, out, err = run_cli(capsys, *argv)
        assert code == 2 and out == "" and upgrade in one_sentence(err), argv
    scores = tmp_path / "scores.csv"
    pd.read_csv(old / "orb-nn" / "pairs.csv")[["query", "reference", "label", "score"]].to_csv(scores, index=False)
    argv = ["import-scores", str(scores), "--sequence", "photos", "--method", "ext", "--output-dir", str(old)]
    code, _, err = run_cli(capsys, *argv)
    assert code == 2 and upgrade in one_sentence(err)
    params = config.load_params(params_file(tmp_path, output_dir=str(old)))
    with pytest.raises(Exception, match="upgrade"):  # a stage notebook on its own
        method_runs.run_method_of_params(params, sequence_build.prepare_sequence(params), "orb-nn", progress=False)
    assert snapshot(old) == before
    # `upgrade` takes it in as one run, deleting and changing nothing; the folder then reads as before.
    code, out, _ = run_cli(capsys, "upgrade", str(old))
    assert code == 0 and "orb-nn" in out
    assert {k: v for k, v in snapshot(old).items() if not k.startswith("runs/")} == before
    (run,), copied = run_ids(old), snapshot(old / "runs" / run_ids(old)[0] / "orb-nn")
    assert "-upgrade-" in run and copied["pairs.csv"] == before["orb-nn/pairs.csv"]
    code, out, _ = run_cli(capsys, "results", str(old))
    table = pd.read_csv(old / "orb-nn" / "pairs.csv")
    ap = evaluate_scores(table["label"].to_numpy(), table["score"].to_numpy())["ap"]
    assert code == 0 and helpers.shown(old) == {"orb-nn": ("repository", 4)}
    assert pd.read_csv(old / "results.csv")["ap"].item() == pytest.approx(ap, abs=1e-6)
    assert run_cli(capsys, "run", str(params_file(tmp_path, output_dir=str(old))))[0] == 0  # a run adds to it


# ------------------------------------------------------------ every door adds --
def test_every_door_adds_a_run_and_changes_no_byte_of_the_earlier_ones(tmp_path, root, capsys, notebooks_here):
    out, path = tmp_path / "out", params_file(tmp_path)
    scores = tmp_path / "scores.csv"
    doors = [
        ("run", lambda: run_cli(capsys, "run", str(path))),
        ("run", lambda: run_cli(capsys, "run", str(path))),  # a rerun
        ("run", lambda: run_cli(capsys, "run", str(path), "--limit", "2")),
        ("02_verify", lambda: helpers.verify_on_its_own(path, "sift-opencv-nn")),
        ("shard", lambda: run_cli(capsys, "run", str(path), "--shard", "0/2")),
        ("shard", lambda: run_cli(capsys, "run", str(path), "--shard", "1/2")),
        ("merge", lambda: run_cli(capsys, "run", str(path), "--merge")),
        ("import", lambda: run_cli(capsys, "import-scores", str(scores), "--sequence", "photos", "--method", "ext",
                                   "--output-dir", str(out))),
    ]  # fmt: skip
    for door, go in doors:
        if door == "import":
            table = pd.read_csv(method_outputs.method_dir(out, "orb-nn") / "pairs.csv")
            table[["query", "reference", "label", "score"]].to_csv(scores, index=False)
        before = runs_files(out)
        said = go()
        assert said is None or said[0] == 0, said
        helpers.added_one_run(out, before, door)
    assert check_runs_whole(out) == run_ids(out) and len(run_ids(out)) == len(doors)
    assert set(helpers.shown(out)) == {"orb-nn", "sift-opencv-nn", "ext"}


@pytest.mark.slow
def test_two_runs_started_together_on_one_folder_both_land_whole(tmp_path, root):
    """Runs A and B (the real notebooks, each a process of its own) on one folder at once, B with every
    label flipped: both land whole, each printing its own AP, and a reader polling meanwhile sees whole runs."""
    out = tmp_path / "out"
    env = {**os.environ, "PYTHONPATH": str(config.PROJECT_ROOT)}
    started = {
        name: subprocess.Popen(
            [sys.executable, "-m", "gvbench_nb", "run", str(params_file(tmp_path, f"{name}.yaml", pairs))],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            env=env,
        )  # fmt: skip
        for name, pairs in (("a", PAIRS), ("b", FLIPPED))
    }
    polls = []  # the AP a reader of the folder found, as `results` reads it, while the runs ran
    while any(p.poll() is None for p in started.values()):
        if check_runs_whole(out) if (out / "runs").is_dir() else False:
            polls.append(scoring.evaluate(out, scoring.readable_methods(out), write=False)["ap"].item())
        time.sleep(0.2)
    said = {name: p.communicate() for name, p in started.items()}
    assert all(p.returncode == 0 for p in started.values()), said
    ids, aps = check_runs_whole(out), []
    assert len(ids) == 2
    for run_id in ids:
        params = yaml.safe_load((out / "runs" / run_id / "params.resolved.yaml").read_text())
        name = Path(params["pairs"]).stem.removesuffix("-pairs")
        table = pd.read_csv(out / "runs" / run_id / "orb-nn" / "pairs.csv")
        assert table["label"].tolist() == [p.label for p in (PAIRS if name == "a" else FLIPPED)]
        run_table = pd.read_csv(out / "runs" / run_id / "results.csv")
        alone = evaluate_scores(table["label"].to_numpy(), table["score"].to_numpy())["ap"]
        assert run_table["ap"].item() == pytest.approx(alone, abs=1e-6)  # the run's own table is its own
        aps.append(alone)
    assert all(min(abs(ap - a) for a in aps) < 1e-6 for ap in polls), (polls, aps)  # each poll one run's


# ------------------------------------------------------ failed or killed runs --
@pytest.mark.parametrize("failing", ["02_verify.ipynb", "03_evaluate.ipynb"])
def test_a_failed_rerun_leaves_the_earlier_runs_and_the_table_as_they_were(
    tmp_path, root, capsys, monkeypatch, notebooks_here, failing
):
    out, path = tmp_path / "out", params_file(tmp_path)
    assert run_cli(capsys, "run", str(path))[0] == 0
    before, table = runs_files(out), (out / "results.csv").read_bytes()

    def fails_in(name, output_path, parameters):
        if name == failing:
            output_path.write_text("the executed notebook, with its traceback")
            raise RuntimeError(f"{name} failed")
        in_process_notebooks(name, output_path, parameters)

    monkeypatch.setattr(run_and_publish, "execute_notebook", fails_in)
    with pytest.raises(RuntimeError, match="failed"):
        cli.main(["run", str(path), "--methods", "orb-nn,sift-opencv-nn"])
    err = capsys.readouterr().err
    (building,) = (out / "runs").glob(".building-*")
    assert f"{out} shows what it showed before; this run's partial work and executed notebooks are in {building}" in err
    executed = failing.replace(".ipynb", "_orb-nn.ipynb" if "02" in failing else ".ipynb")
    assert (building / executed).is_file()
    assert runs_files(out) == before and (out / "results.csv").read_bytes() == table
    code, text, _ = run_cli(capsys, "results", str(out))
    assert code == 0 and "orb-nn" in text and "sift-opencv-nn" not in text


@pytest.mark.slow
def test_ctrl_c_during_a_run_keeps_the_earlier_runs(tmp_path, root):
    out, path = tmp_path / "out", params_file(tmp_path)
    env = {**os.environ, "PYTHONPATH": str(config.PROJECT_ROOT)}
    subprocess.run([sys.executable, "-m", "gvbench_nb", "run", str(path)], check=True, env=env, capture_output=True)
    (first,), before, table = run_ids(out), runs_files(out), (out / "results.csv").read_bytes()
    second = subprocess.Popen(
        [sys.executable, "-m", "gvbench_nb", "run", str(path), "--methods", "orb-nn,sift-opencv-nn"],
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
    )
    deadline = time.monotonic() + 120
    while not list((out / "runs").glob(".building-*/01_sequence.ipynb")) and time.monotonic() < deadline:
        time.sleep(0.05)
    second.send_signal(signal.SIGINT)
    second.communicate(timeout=120)
    assert second.returncode != 0
    assert runs_files(out) == before and (out / "results.csv").read_bytes() == table
    assert check_runs_whole(out) == [first]


KILLED_RUN = """
import os, signal, sys
sys.path.insert(0, {tests!r})
import contextlib
import helpers
from gvbench_nb import cli, run_and_publish
from gvbench_nb.runner import method_runs, runs
run_and_publish.execute_notebook = helpers.in_process_notebooks
run_and_publish.kernels_ahead = lambda count: contextlib.nullcontext()


def stopping(function, before=False):  # the process stops itself there, to be killed
    def call(*args, **kwargs):
        if before:
            os.kill(os.getpid(), signal.SIGSTOP)
        result = function(*args, **kwargs)
        os.kill(os.getpid(), signal.SIGSTOP)
        return result
    return call

stop = {stop!r}
if stop == "as its run is started":
    runs.start = stopping(runs.start)
elif stop == "as its first method is written":
    method_runs.write_results = stopping(method_runs.write_results)
elif stop in ("just before the rename", "just after the rename"):  # runs.finish's one rename
    os.rename = stopping(os.rename, before=stop == "just before the rename")
sys.exit(cli.main(["run", {params!r}, "--methods", "orb-nn,sift-opencv-nn"]))
"""


def stopped(pid: int) -> bool:
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] == "T"
    except OSError:
        return False


@pytest.mark.slow
@pytest.mark.parametrize(
    "moment",
    [
        0.5,
        2.0,
        "as its run is started",
        "as its first method is written",
        "just before the rename",
        "just after the rename",
    ],
    ids=str,
)
def test_a_run_killed_at_any_moment_leaves_every_finished_run_whole(tmp_path, root, capsys, notebooks_here, moment):
    """kill -9 of a ``run`` (its notebooks computed in its process) after some seconds, or at a point where it
    stops itself: the earlier run is byte-identical, and every finished run whole."""
    out, path = tmp_path / "out", params_file(tmp_path)
    assert run_cli(capsys, "run", str(path))[0] == 0
    before, ids = runs_files(out), run_ids(out)
    assert len(ids) == 1
    script = KILLED_RUN.format(tests=str(Path(__file__).parent.parent), params=str(path), stop=moment)
    env = {**os.environ, "PYTHONPATH": str(config.PROJECT_ROOT)}
    killed = subprocess.Popen([sys.executable, "-c", script], env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    started = time.monotonic()
    while killed.poll() is None and not (
        stopped(killed.pid) if isinstance(moment, str) else time.monotonic() - started > moment
    ):
        time.sleep(0.01)
    killed.send_signal(signal.SIGKILL)
    _, err = killed.communicate(timeout=60)
    assert killed.returncode == -signal.SIGKILL, err.decode()[-2000:]  # killed, not finished
    after = runs_files(out)
    assert {name: after.get(name) for name in before} == before
    landed = 1 if moment == "just after the rename" else 0 if isinstance(moment, str) else None
    assert check_runs_whole(out)[:1] == ids and len(run_ids(out)) - 1 in ((0, 1) if landed is None else (landed,))
    code, text, _ = run_cli(capsys, "results", str(out))
    assert code == 0 and "orb-nn" in text
    assert run_cli(capsys, "run", str(path))[0] == 0  # the next run is not in the killed one's way


def test_a_run_refused_before_work_leaves_nothing_and_names_the_params_file_once(
    tmp_path, root, capsys, notebooks_here
):
    no_root = params_file(tmp_path, "no-root.yaml", image_root=str(tmp_path / "no-such-images"))
    code, _, err = run_cli(capsys, "run", str(no_root))
    assert code == 2 and err.count(str(no_root)) == 1, err
    assert not (tmp_path / "out").exists() and not (tmp_path / "cache").exists()
    # A mistyped pair file keeps the finished run.
    path = params_file(tmp_path)
    assert run_cli(capsys, "run", str(path))[0] == 0
    before = snapshot(tmp_path / "out")
    typo = params_file(tmp_path, "typo.yaml")
    typo.write_text(yaml.safe_dump({**yaml.safe_load(typo.read_text()), "pairs": str(tmp_path / "params-pairs.txtt")}))
    code, _, err = run_cli(capsys, "run", str(typo))
    assert code == 2 and "does not exist" in one_sentence(err)
    assert snapshot(tmp_path / "out") == before
    assert run_cli(capsys, "results", str(tmp_path / "out"))[0] == 0


# ---------------------------------------------------------------- the view --
def test_the_folder_shows_each_methods_latest_run_on_the_current_inputs_and_names_what_it_left_out(
    tmp_path, root, capsys, notebooks_here
):
    out, path = tmp_path / "out", params_file(tmp_path, methods=["orb-nn", "sift-opencv-nn"])
    assert run_cli(capsys, "run", str(path))[0] == 0
    assert helpers.shown(out) == {"orb-nn": ("repository", 4), "sift-opencv-nn": ("repository", 4)}
    # Another recipe for one method: the folder shows both, a row each, and still the other method.
    code, text, err = run_cli(capsys, "run", str(path), "--methods", "orb-nn", "--profile", "paper")
    first = run_ids(out)[0]
    rows = {"orb-nn (paper profile)": ("paper", 4), "orb-nn (repository profile)": ("repository", 4)}
    assert code == 0 and helpers.shown(out) == {**rows, "sift-opencv-nn": ("repository", 4)}
    assert helpers.not_in_table(err) == [] and f"sift-opencv-nn of run {first}" in text
    code, text, err = run_cli(capsys, "results", str(out))
    assert code == 0 and all(row in text for row in [*rows, "sift-opencv-nn"]) and helpers.not_in_table(err) == []
    # Other labels: the latest run's pairs are the folder's; the paper run is left out for its pairs.
    flipped = params_file(tmp_path, "flipped.yaml", FLIPPED, methods=["sift-opencv-nn"])
    code, _, err = run_cli(capsys, "run", str(flipped))
    paper = run_ids(out)[1]
    assert code == 0 and helpers.shown(out) == {"sift-opencv-nn": ("repository", 4)}
    assert helpers.not_in_table(err) == [
        f"not in this table: orb-nn ({profile} profile): its latest run {run} scored 4 other pairs or labels "
        f"(results {out} --run {run})"
        for profile, run in (("repository", first), ("paper", paper))
    ]
    assert pd.read_csv(method_outputs.method_dir(out, "sift-opencv-nn") / "pairs.csv")["label"].tolist() == [
        p.label for p in FLIPPED
    ]


def test_results_of_an_earlier_run_by_its_id(tmp_path, root, capsys, notebooks_here):
    out = tmp_path / "out"
    assert run_cli(capsys, "run", str(params_file(tmp_path)))[0] == 0
    assert run_cli(capsys, "run", str(params_file(tmp_path, "flipped.yaml", FLIPPED)))[0] == 0
    first, second = run_ids(out)
    aps = {}
    for run_id in (first, second):
        table = pd.read_csv(out / "runs" / run_id / "orb-nn" / "pairs.csv")
        aps[run_id] = evaluate_scores(table["label"].to_numpy(), table["score"].to_numpy())["ap"]
    assert aps[first] != pytest.approx(aps[second])  # the labels flipped
    code, text, _ = run_cli(capsys, "results", str(out), "--run", first)
    row = next(line.split() for line in text.splitlines() if line.startswith("orb-nn"))
    assert code == 0 and float(row[3]) == pytest.approx(aps[first], abs=1e-3), text
    code, text, _ = run_cli(capsys, "results", str(out))
    row = next(line.split() for line in text.splitlines() if line.startswith("orb-nn"))
    assert code == 0 and float(row[3]) == pytest.approx(aps[second], abs=1e-3)
    code, text, err = run_cli(capsys, "results", str(out), "--run", "20001231T000000-run-abcdef")
    assert code == 2 and text == "" and "is not a run of" in one_sentence(err) and first in err and second in err
    # A run is read, never written: a run into it is refused, and it stays as it was.
    before = runs_files(out)
    code, _, err = run_cli(capsys, "run", str(params_file(tmp_path)), "--output-dir", str(out / "runs" / first))
    assert code == 2 and f"is a run of the output folder {out}" in one_sentence(err) and runs_files(out) == before
    assert not list((out / "runs" / first).glob("runs"))


def test_results_and_the_report_refuse_methods_scored_on_different_labels_naming_them(tmp_path, root, capsys):
    from gvbench_nb.runner import runs

    out, cache, pair_tables = tmp_path / "out", tmp_path / "cache", {}
    with runs.new_run(out, "notebook") as building:  # one run whose methods scored different labels
        for method, pairs in (("orb-nn", PAIRS), ("sift-opencv-nn", FLIPPED)):
            pair_tables[method] = method_runs.run_method(
                Sequence("photos", root, pairs), method, "repository", building, cache, device="cpu", progress=False
            )
    (run,) = run_ids(out)
    code, out_text, err = run_cli(capsys, "results", str(out), "--run", run)
    assert code == 2 and out_text == ""
    assert "scored on different pairs or labels (orb-nn: pairs" in one_sentence(err) and "sift-opencv-nn: pairs" in err
    with pytest.raises(method_outputs.ResultsError, match="label 4 of the same pairs differently"):
        run_tables.align_tables(pair_tables)  # the report never scores one method against another's labels
    # The explore notebook's reader refuses them too, and reads one method alone.
    with pytest.raises(method_outputs.ResultsError, match="scored on different pairs or labels"):
        run_tables.load_pairs_tables(out / "runs" / run)
    assert list(run_tables.load_pairs_tables(out / "runs" / run, ["orb-nn"])) == ["orb-nn"]


@pytest.mark.parametrize("changed", ["label", "image"])
def test_results_refuses_results_whose_inputs_changed_since_the_run(tmp_path, root, capsys, notebooks_here, changed):
    assert run_cli(capsys, "run", str(params_file(tmp_path)))[0] == 0
    pairs_file = tmp_path / "params-pairs.txt"
    if changed == "label":
        write_pairs(pairs_file, [PAIRS[0], Pair(PAIRS[1].query, PAIRS[1].reference, 1), *PAIRS[2:]])
    else:
        (root / "query" / "a.png").write_bytes((root / "query" / "b.png").read_bytes())
    code, out, err = run_cli(capsys, "results", str(tmp_path / "out"))
    assert code == 2 and out == ""
    expected = f"the pair file {pairs_file} changed" if changed == "label" else f"images under {root} changed"
    assert f"orb-nn: {expected}" in one_sentence(err)


# ---------------------------------------------------------------- the table --
def test_the_folder_table_lists_every_method_run_one_at_a_time(tmp_path, root, capsys, notebooks_here):
    path = params_file(tmp_path)
    assert run_cli(capsys, "run", str(path), "--methods", "orb-nn")[0] == 0
    code, out, _ = run_cli(capsys, "run", str(path), "--methods", "sift-opencv-nn")
    assert code == 0
    results = pd.read_csv(tmp_path / "out" / "results.csv")
    assert sorted(results["method"]) == ["orb-nn", "sift-opencv-nn"]
    assert "orb-nn" in out and "sift-opencv-nn" in out  # the table `run` prints is the folder's
    kept = json.loads((method_outputs.method_dir(tmp_path / "out", "orb-nn") / "run.json").read_text())
    assert kept["binding"]["pairs_digest"] == scoring.pairs_digest((p.query, p.reference, p.label) for p in PAIRS)
    assert kept["run_id"] == run_ids(tmp_path / "out")[0]


# ------------------------------------------------------------------- timers --
def test_a_rerun_served_from_the_cache_says_its_timers_are_the_earlier_runs(tmp_path, root, capsys, notebooks_here):
    path = params_file(tmp_path)
    code, out, _ = run_cli(capsys, "run", str(path))
    assert code == 0 and pd.read_csv(tmp_path / "out" / "results.csv")["timers"].tolist() == ["this run"]
    assert "came from the cache" not in out
    # The same run again (as `make demo` after `make test`'s notebooks): every image and pair is cached.
    code, out, _ = run_cli(capsys, "run", str(path))
    assert code == 0 and pd.read_csv(tmp_path / "out" / "results.csv")["timers"].tolist() == ["cached"]
    assert "orb-nn: images or pairs came from the cache, so their seconds are those of the runs" in out
    # Another folder shares the cache folder, its match stores included: nothing is computed again.
    other = params_file(tmp_path, "demo.yaml", output_dir=str(tmp_path / "demo"))
    assert run_cli(capsys, "run", str(other))[0] == 0
    assert pd.read_csv(tmp_path / "demo" / "results.csv")["timers"].tolist() == ["cached"]


def test_two_runs_of_one_process_within_a_second_have_their_own_run_ids(tmp_path, monkeypatch):
    # A run's timers count the images it extracted itself by its id: two ids must never meet.
    import datetime

    from gvbench_nb.runner import runs

    class OneSecond(datetime.datetime):  # both runs started in the same second, whatever the load
        @classmethod
        def now(cls, tz=None):
            return datetime.datetime(2026, 12, 4, 12, 0, 0, tzinfo=tz)

    monkeypatch.setattr(runs._dt, "datetime", OneSecond)
    first, second = (runs.run_id(runs.start(tmp_path, "run")) for _ in range(2))
    assert first.split("-")[0] == second.split("-")[0] == "20261204T120000" and first != second


def test_results_fits_100_columns_and_shows_every_column_when_wide(tmp_path, root, capsys, notebooks_here):
    methods = ["--methods", "orb-nn,sift-opencv-nn", "--limit", "3"]
    assert run_cli(capsys, "run", str(params_file(tmp_path)), *methods)[0] == 0
    code, out, _ = run_cli(capsys, "results", str(tmp_path / "out"))
    assert code == 0 and max(map(len, out.splitlines()[1:])) <= 100, out  # all but the folder's path
    assert ", the first 3 pairs (--limit)" in out.splitlines()[1]
    assert " ".join(out.splitlines()[4].split()) == "method profile n_pairs AP [95% CI] MR [95% CI] s/pair"
    code, out, _ = run_cli(capsys, "results", str(tmp_path / "out"), "--wide")
    assert out.splitlines()[4].split() == tables.WIDE_COLUMNS
    code, out, _ = run_cli(capsys, "results", str(tmp_path / "out"), "--markdown")
    assert out.splitlines()[4] == "| " + " | ".join(tables.WIDE_COLUMNS) + " |"  # the README's tables come from it


def test_images_another_method_of_the_same_run_extracted_are_timed_by_this_run(tmp_path, root):
    """xfeat-nn and xfeat-lg share their features: the second method of one run finds them cached,
    but this run extracted and timed them, so its timers are this run's; another run's are not."""
    from gvbench_nb import methods
    from gvbench_nb.runner import image_features

    sequence, cache = Sequence("photos", root, PAIRS), tmp_path / "cache"
    conf = methods.resolve_method("orb-nn", "repository")["extractor"]

    def extraction(run_id: str) -> dict[str, int]:
        return image_features.extract_features(sequence, conf, cache, "cpu", progress=False, run_id=run_id)

    first = extraction("run-1")
    assert first["extracted"] == first["images"] > 0 and "cached_by_this_run" not in first
    later_method, next_run = extraction("run-1"), extraction("run-2")
    assert later_method["cached"] == later_method["cached_by_this_run"] == first["images"]
    assert next_run["cached"] == first["images"] and "cached_by_this_run" not in next_run
    matched = {"cached": 0, "matched": len(PAIRS)}
    assert scoring.timers_source({"this_run": {"extraction": later_method, "matching": matched}}) == "this run"
    assert scoring.timers_source({"this_run": {"extraction": next_run, "matching": matched}}) == "partly cached"
