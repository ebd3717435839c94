"""A run is sealed: its manifest lists every file with its size and hash, and every read of a run goes
through that list. Also what the doors say about runs: ``--run`` takes one whole id, ``run`` prints its
own table and says when it landed though a later write failed, a method shows under every recipe it
ran, and unfinished builds are named and cleaned. docs/reliability.md, section 3, lists each test."""

from __future__ import annotations

import contextlib
import errno
import json
import os
import subprocess
import sys
import time

import pandas as pd
import pytest
from helpers import PAIRS, in_process_notebooks, one_sentence, params_file, run_cli, run_ids
from written_runs import add_run

from gvbench_nb import run_and_publish
from gvbench_nb.protocol.metrics import evaluate_scores
from gvbench_nb.runner import runs, scoring

pytestmark = pytest.mark.reliability

ENVIRONMENT = {"device": "cpu", "device_name": "a CPU", "cpu_count": 2, "torch": "t", "kornia": "k", "opencv": "o"}


@pytest.fixture
def notebooks_here(monkeypatch):
    monkeypatch.setattr(run_and_publish, "execute_notebook", in_process_notebooks)
    monkeypatch.setattr(run_and_publish, "kernels_ahead", lambda count: contextlib.nullcontext())


def toy_table(labels: list[int], scores: list[float]) -> pd.DataFrame:
    n = len(labels)
    pairs = {
        "pair_index": range(n),
        "query": [f"q{i // 2}" for i in range(n)],
        "reference": [f"r{i}" for i in range(n)],
    }
    timers = {"extract_seconds": 0.1, "match_seconds": 0.1, "verify_seconds": 0.1, "num_inliers": 10}
    return pd.DataFrame(pairs | {"label": labels, "score": scores} | timers)


def toy_run(out, method: str, table: pd.DataFrame, profile: str = "repository", seed: int = 0, **conf) -> str:
    """A hand-written run of ``method`` holding ``table``; returns its id."""
    digest = scoring.table_pairs_digest(table)
    record = {"binding": {"pairs_digest": digest}, "n_pairs": len(table), "seed": seed, "environment": ENVIRONMENT}
    record |= {"finished_at": "2026-12-08T00:00:00+00:00", "conf": {"profile": profile, **conf}}
    return add_run(out, method, table, record).parent.name


LABELS, SCORES = [1, 0, 1, 0, 1, 0, 0, 1], [9.0, 1.0, 7.0, 8.0, 6.0, 2.0, 3.0, 5.0]


@pytest.fixture
def two_runs(tmp_path):
    """Two runs of orb-nn on one folder, the second with other scores; their ids."""
    out = tmp_path / "out"
    first = toy_run(out, "orb-nn", toy_table(LABELS, SCORES))
    second = toy_run(out, "orb-nn", toy_table(LABELS, SCORES[::-1]))
    return out, first, second


def damage(run, how: str) -> str:
    """Damage one file of ``run`` as a user or a disk might; the file's name in the run."""
    if how in ("a label flipped", "a score edited"):
        path = run / "orb-nn" / "pairs.csv"
        table = pd.read_csv(path)
        column, value = ("label", 1 - table["label"][1]) if how == "a label flipped" else ("score", 4.0)
        table.loc[1, column] = value
        table.to_csv(path, index=False)
        return "orb-nn/pairs.csv"
    if how == "run.json moved away":
        (run / "orb-nn" / "run.json").rename(run.parent.parent / "run.json")
        return "orb-nn/run.json"
    if how == "a file added":
        (run / "notes.txt").write_text("mine")
        return "notes.txt"
    manifest = run / "manifest.json"
    data = manifest.read_bytes()
    manifest.write_bytes(data[: len(data) // 2] if how == "manifest cut short" else data.replace(b'"run"', b'"merge"'))
    return "manifest.json"


@pytest.mark.parametrize(
    "how",
    [
        "a label flipped",
        "a score edited",
        "run.json moved away",
        "a file added",
        "manifest cut short",
        "manifest edited",
    ],
)
def test_a_damaged_run_is_refused_naming_run_and_file_and_never_lets_an_earlier_run_look_current(
    two_runs, tmp_path, capsys, root, notebooks_here, how
):
    out, first, second = two_runs
    name = damage(out / "runs" / second, how)
    said = f"run {second} of {out}: its {name} "
    for argv in (["results", str(out)], ["compare", str(out)], ["results", str(out), "--run", second]):
        code, text, err = run_cli(capsys, *argv)
        assert (
            code == 2
            and text == ""
            and said in one_sentence(err)
            and f"remove the folder {out / 'runs' / second}" in err
        )
    with pytest.raises(runs.RunsError, match=said):
        runs.current(out)  # the view every reader goes through, never the earlier run's
    code, _, err = run_cli(capsys, "run", str(params_file(tmp_path)))  # the next run: refused before work
    assert code == 2 and said in one_sentence(err) and set(os.listdir(out / "runs")) == {first, second}
    code, text, _ = run_cli(capsys, "results", str(out), "--run", first)  # the whole run asked for by id
    assert code == 0 and "orb-nn" in text


def test_each_file_of_a_run_is_hashed_once_a_process(two_runs, monkeypatch):
    out, _, _ = two_runs
    hashed, hash_file = [], runs.hash_file
    monkeypatch.setattr(runs, "_digests", {})
    monkeypatch.setattr(runs, "hash_file", lambda path, digest: hashed.append(path) or hash_file(path, digest))
    runs.current(out)
    files = len(hashed)
    assert files == len(list((out / "runs").rglob("*.*"))) - 2  # every file but the two manifests
    runs.current(out)
    scoring.evaluate(out, write=False)
    assert len(hashed) == files


@pytest.mark.parametrize("wanted", ["", "partial"])
def test_run_takes_one_whole_id_and_refuses_an_empty_or_partial_one_naming_the_runs(two_runs, capsys, wanted):
    out, first, second = two_runs
    wanted = first[:-4] if wanted else ""
    code, text, err = run_cli(capsys, "results", str(out), "--run", wanted)
    assert code == 2 and text == "" and first in one_sentence(err)
    assert ("--run is empty" in err and second in err) if not wanted else "give a whole id" in err


def test_a_run_prints_its_own_table_when_another_run_lands_before_it_prints(
    tmp_path, root, capsys, monkeypatch, notebooks_here
):
    out, finish, landed = tmp_path / "out", runs.finish, []

    def another_lands_meanwhile(building, **details):
        run = finish(building, **details)
        if not landed:  # run B lands between run A's rename and its table
            landed.append(True)
            table = pd.read_csv(run / "orb-nn" / "pairs.csv")
            flipped = table.assign(label=1 - table["label"])
            landed.append(toy_run(out, "orb-nn", flipped))
        return run

    monkeypatch.setattr(runs, "finish", another_lands_meanwhile)
    code, text, _ = run_cli(capsys, "run", str(params_file(tmp_path)))
    own = pd.read_csv(out / "runs" / run_ids(out)[0] / "orb-nn" / "pairs.csv")
    ap = evaluate_scores(own["label"].to_numpy(), own["score"].to_numpy())["ap"]
    row = next(line.split() for line in text.splitlines() if line.startswith("orb-nn"))
    assert code == 0 and float(row[4]) == pytest.approx(ap, abs=1e-3), text
    assert f"{out} shows not this run but orb-nn of run {landed[1]}" in text


def test_a_failure_after_the_rename_says_the_run_landed(tmp_path, root, capsys, monkeypatch, notebooks_here):
    out = tmp_path / "out"

    def disk_full(path, frame):  # the folder's table, after the run's rename
        if path.parent == out:
            raise OSError(errno.ENOSPC, "No space left on device", str(path))
        write(path, frame)

    write = scoring.atomic_write_csv

    monkeypatch.setattr(scoring, "atomic_write_csv", disk_full)
    code, _, err = run_cli(capsys, "run", str(params_file(tmp_path)))
    (run,) = run_ids(out)
    last = err.strip().splitlines()[-1]
    assert code == 2 and last.startswith(f"error: run {run} landed in {out}; writing the folder's results.csv failed")
    assert "No space left on device" in last and f"`python -m gvbench_nb results {out}` makes it again" in last
    monkeypatch.undo()
    assert run_cli(capsys, "results", str(out))[0] == 0 and (out / "results.csv").is_file()


def test_a_method_shows_a_row_under_every_recipe_it_ran_and_what_is_left_out_is_said_in_words(tmp_path, capsys):
    out, table = tmp_path / "out", toy_table(LABELS, SCORES)
    toy_run(out, "orb-nn", table)
    toy_run(out, "orb-nn", table, profile="paper")
    toy_run(out, "orb-nn", table, seed=1)
    toy_run(out, "sift-opencv-nn", table)
    rows = [
        "orb-nn (repository profile; seed 0)",
        "orb-nn (paper profile; seed 0)",
        "orb-nn (repository profile; seed 1)",
    ]
    code, text, err = run_cli(capsys, "results", str(out))
    assert code == 0 and all(row in text for row in rows) and "not in this table" not in err
    assert sorted(pd.read_csv(out / "results.csv")["method"]) == sorted([*rows, "sift-opencv-nn"])
    assert set(runs.current(out).entries) == {*rows, "sift-opencv-nn"}
    assert [entry.recipe["profile"] for entry in runs.current(out).of("orb-nn")] == [
        "repository",
        "paper",
        "repository",
    ]
    # Other labels: the rows of the earlier pairs are left out, each named in words.
    toy_run(out, "sift-opencv-nn", toy_table(LABELS[::-1], SCORES))
    code, text, err = run_cli(capsys, "results", str(out))
    left = [line for line in err.splitlines() if line.startswith("not in this table: ")]
    assert code == 0 and len(left) == 3 and all(row in err for row in rows)
    assert not any(mark in err for mark in "{}[]'")


def test_unfinished_builds_are_named_and_clean_removes_only_those_no_process_builds(tmp_path, capsys):
    out = tmp_path / "out"
    first = toy_run(out, "orb-nn", toy_table(LABELS, SCORES))
    alive = runs.start(out, "run")  # this process builds it
    ended = runs.start(out, "run")
    gone = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    manifest = json.loads((ended / "manifest.json").read_text())
    (ended / "manifest.json").write_text(json.dumps(manifest | {"pid": int(gone.stdout)}))
    earlier = out / "runs" / ".building-20261201T000000-run-abcdef"  # an earlier version's, untouched for two days
    (earlier / "orb-nn").mkdir(parents=True)
    (earlier / "orb-nn" / "pairs.csv").write_bytes(b"x" * 2_000_000)
    for path in (earlier / "orb-nn" / "pairs.csv", earlier / "orb-nn", earlier):
        os.utime(path, (time.time() - 2 * 86400,) * 2)
    code, _, err = run_cli(capsys, "results", str(out))
    line = f"{out} holds 3 unfinished runs (runs/.building-*, 2.0 MB), 2 abandoned: `python -m gvbench_nb clean {out}`"
    assert code == 0 and line in err
    code, text, _ = run_cli(capsys, "clean", str(out))
    assert code == 0 and "removed 2" in text and runs.unfinished(out) == [alive] and run_ids(out) == [first]
    # --superseded: also the finished runs the folder no longer shows.
    later = toy_run(out, "orb-nn", toy_table(LABELS[::-1], SCORES))
    assert run_cli(capsys, "clean", str(out))[0] == 0 and run_ids(out) == [first, later]
    code, text, _ = run_cli(capsys, "clean", str(out), "--superseded")
    assert code == 0 and first in text and run_ids(out) == [later] and runs.unfinished(out) == [alive]


def test_upgrade_of_a_publication_stopped_half_way_takes_in_what_the_earlier_version_would_have(tmp_path, capsys):
    """The earlier layout published a stage by moving its files one by one into the folder, its record
    saying ``publishing`` meanwhile; killed half way, the folder holds the new pairs.csv beside the old run.json."""
    old, stage = tmp_path / "old", tmp_path / "old" / ".run-20261201T120000Z-1-abcdef"
    (old / "orb-nn").mkdir(parents=True)
    (stage / "orb-nn").mkdir(parents=True)
    toy_table(LABELS, SCORES).to_csv(old / "orb-nn" / "pairs.csv", index=False)  # moved already
    (old / "orb-nn" / "run.json").write_text(json.dumps({"conf": {"profile": "repository"}}))  # the earlier run's
    (stage / "orb-nn" / "run.json").write_text(json.dumps({"conf": {"profile": "paper"}}))  # not moved yet
    files = ["orb-nn/pairs.csv", "orb-nn/run.json"]
    record = {"package": "gvbench-nb", "state": "publishing", "stage": stage.name}
    record["next"] = {"files": files, "methods": {"orb-nn": {}}, "run_id": "20261201T120000Z-1-abcdef"}
    (old / "gvbench-run.json").write_text(json.dumps(record))
    print(runs.upgrade(old))
    (run,) = run_ids(old)
    taken = old / "runs" / run / "orb-nn"
    assert json.loads((taken / "run.json").read_text())["conf"]["profile"] == "paper"
    assert (taken / "pairs.csv").read_bytes() == (old / "orb-nn" / "pairs.csv").read_bytes()
    assert f"finishing the publication {stage.name}" in capsys.readouterr().out


def test_runs_written_before_runs_were_sealed_are_refused_naming_upgrade_which_seals_them(two_runs, capsys):
    out, first, second = two_runs
    for run in (first, second):
        path = out / "runs" / run / "manifest.json"
        manifest = json.loads(path.read_text())
        path.write_text(json.dumps({k: v for k, v in manifest.items() if k not in ("files", "seal")}))
    code, _, err = run_cli(capsys, "results", str(out))
    assert code == 2 and f"python -m gvbench_nb upgrade {out}" in one_sentence(err) and "before runs were sealed" in err
    code, text, _ = run_cli(capsys, "upgrade", str(out))
    assert code == 0 and "sealed 2 runs" in text
    assert run_cli(capsys, "results", str(out))[0] == 0


def test_make_clean_removes_what_the_package_writes_and_not_the_dead_cache_folder():
    makefile = (runs.Path(__file__).parents[2] / "Makefile").read_text()
    recipe = makefile.split("\nclean:\n", 1)[1].split("\n\n", 1)[0]
    assert "outputs/cache" not in recipe and "-m gvbench_nb clean" in recipe and "outputs/data" in recipe


def hashing_cost(folder) -> tuple[int, float, float]:
    """A 2,000-pair run's pairs.csv (every column, Gardens Point's names): its size, and the seconds to check
    the run the first time and once its files are hashed (for docs/reliability.md, never asserted)."""
    import numpy as np

    from gvbench_nb.runner import method_outputs

    n, rng = 2000, np.random.default_rng(0)
    table = pd.DataFrame({column: rng.random(n) for column in method_outputs.PAIRS_COLUMNS})
    table["query"], table["reference"] = (
        [f"{side}/Image{i:03d}.jpg" for i in range(n)] for side in ("night_right", "day_left")
    )
    run = add_run(folder, "orb-nn", table.assign(label=rng.integers(0, 2, n), method="orb-nn")).parent
    runs._digests.clear()
    started = time.perf_counter()
    runs.sealed(run)
    cold = time.perf_counter() - started
    started = time.perf_counter()
    runs.sealed(run)
    return (run / "orb-nn" / "pairs.csv").stat().st_size, cold, time.perf_counter() - started


def test_run_json_says_each_thing_once(tmp_path, root, capsys, notebooks_here):
    path = params_file(tmp_path)
    assert run_cli(capsys, "run", str(path))[0] == 0
    text = (runs.method_folder(tmp_path / "out", "orb-nn") / "run.json").read_text()
    record, pairs_file = json.loads(text), str(tmp_path / "params-pairs.txt")
    assert text.count(pairs_file) == 1 and text.count(record["pairs"]["pairs_sha256"]) == 1
    assert set(record["binding"]) == {"pairs_digest", "images_digest"} and record["n_pairs"] == len(PAIRS)
    assert not {"image_root", "seed"} & set(record["pairs"])  # said once, at the record's top


if __name__ == "__main__":  # python tests/runner/test_sealed_runs.py (with tests/ on PYTHONPATH): the check's cost
    import tempfile
    from pathlib import Path

    with tempfile.TemporaryDirectory() as folder:
        size, cold, warm = hashing_cost(Path(folder))
    print(f"2,000-pair pairs.csv ({size / 1e3:.0f} kB): checked in {cold * 1e3:.2f} ms, again {warm * 1e3:.2f} ms")
