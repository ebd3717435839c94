"""The run record: an output folder is one run's truth, never mixed, never stale, never a user's.
Runs go through ``cli.main`` with the notebooks computed in this process (``in_process_notebooks``),
on four small photographs matched with ORB; docs/reliability.md lists each test beside its promise."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pandas as pd
import pytest
import yaml
from test_fault_injection import write_root

from gvbench_nb import cli, run_and_publish
from gvbench_nb.data.sequences import Pair, Sequence, write_pairs
from gvbench_nb.evaluation import run_tables
from gvbench_nb.protocol.metrics import evaluate_scores
from gvbench_nb.reporting import tables
from gvbench_nb.runner import config, method_outputs, method_runs, record, scoring, sequence_build

pytestmark = pytest.mark.reliability

PAIRS = [
    Pair("query/a.png", "reference/a.png", 1),
    Pair("query/a.png", "reference/b.png", 0),
    Pair("query/b.png", "reference/b.png", 1),
    Pair("query/b.png", "reference/a.png", 0),
]
FLIPPED = [Pair(p.query, p.reference, 1 - p.label) for p in PAIRS]


def in_process_notebooks(name: str, output_path: Path, parameters: dict) -> None:
    """What the stage notebooks compute, here: 02_verify runs its method, 03_evaluate evaluates."""
    params = config.load_params(parameters["params_file"])
    if name == "02_verify.ipynb":
        sequence = sequence_build.prepare_sequence(params)
        method_runs.run_method_of_params(params, sequence, parameters["method"], progress=False)
    elif name == "03_evaluate.ipynb":
        scoring.evaluate(Path(params["output_dir"]), parameters.get("methods"))
    output_path.write_text(json.dumps({"executed": name}))


@pytest.fixture
def notebooks_here(monkeypatch):
    monkeypatch.setattr(run_and_publish, "execute_notebook", in_process_notebooks)


@pytest.fixture
def root(tmp_path) -> Path:
    return write_root(tmp_path / "images")


def params_file(tmp_path: Path, name: str = "params.yaml", pairs: list[Pair] = PAIRS, **changes) -> Path:
    pairs_path = tmp_path / f"{Path(name).stem}-pairs.txt"
    write_pairs(pairs_path, pairs)
    params = {"sequence": "photos", "image_root": str(tmp_path / "images"), "pairs": str(pairs_path)}
    params |= {"methods": ["orb-nn"], "profile": "repository", "device": "cpu"}
    params |= {"output_dir": str(tmp_path / "out"), "cache_dir": str(tmp_path / "cache"), **changes}
    path = tmp_path / name
    path.write_text(yaml.safe_dump(params))
    return path


def run_cli(capsys, *argv: str) -> tuple[int, str, str]:
    capsys.readouterr()
    code = cli.main(list(argv))
    said = capsys.readouterr()
    return code, said.out, said.err


def one_sentence(err: str) -> str:
    assert "Traceback" not in err and len(err.strip().splitlines()) == 1, err
    return err


def snapshot(folder: Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def published_files(folder: Path) -> dict[str, bytes]:
    """``snapshot`` without a run's working state: stages and locks."""
    skipped = (record.STAGE_PREFIX, ".gvbench")
    return {k: v for k, v in snapshot(folder).items() if not k.startswith(skipped)}


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
    assert f"output folder {out} is not empty" in one_sentence(err) and "gvbench-run.json" in err
    assert snapshot(out) == before


def test_a_file_the_package_wrote_and_the_user_edited_is_not_overwritten(tmp_path, root, capsys, notebooks_here):
    path = params_file(tmp_path)
    assert run_cli(capsys, "run", str(path))[0] == 0
    edited = tmp_path / "out" / "results.csv"
    edited.write_text(edited.read_text() + "# my notes\n")
    code, _, err = run_cli(capsys, "run", str(path))
    assert code == 2 and "results.csv" in one_sentence(err) and "changed since" in err
    assert edited.read_text().endswith("# my notes\n")
    # `results` refuses scores edited by hand.
    table = tmp_path / "out" / "orb-nn" / "pairs.csv"
    frame = pd.read_csv(table)
    frame.loc[frame["label"] == 0, "score"] = 0  # a perfect method, by hand
    frame.to_csv(table, index=False)
    code, out, err = run_cli(capsys, "results", str(tmp_path / "out"))
    assert code == 2 and "orb-nn/pairs.csv changed since gvbench-nb wrote them" in one_sentence(err)
    assert out == ""


# --------------------------------------------------------- one writer at a time --
def hold_lock(folder: Path) -> subprocess.Popen:
    """Another process holding the folder's lock, as a running ``run`` does."""
    code = (
        "import sys, time\nfrom gvbench_nb.runner import record\n"
        f"record.FolderLock({str(folder)!r}).acquire()\nprint('held', flush=True)\ntime.sleep(120)\n"
    )
    holder = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True)
    assert holder.stdout is not None and holder.stdout.readline().strip() == "held"
    return holder


def test_a_second_run_on_a_held_folder_is_refused_and_writes_nothing(tmp_path, root, capsys, notebooks_here):
    path = params_file(tmp_path)
    assert run_cli(capsys, "run", str(path))[0] == 0
    before = snapshot(tmp_path / "out")
    holder = hold_lock(tmp_path / "out")
    try:
        flipped = params_file(tmp_path, "flipped.yaml", FLIPPED)
        code, _, err = run_cli(capsys, "run", str(flipped))
        assert code == 2 and f"another run is writing {tmp_path / 'out'} (pid {holder.pid}" in one_sentence(err)
        after = snapshot(tmp_path / "out")
        after.pop(record.HOLDER_NAME)  # the holder's
        assert after == before
        # Meanwhile `results` shows what is published and says a run is writing the folder.
        code, out, err = run_cli(capsys, "results", str(tmp_path / "out"))
        assert code == 0 and "orb-nn" in out and f"a run (pid {holder.pid}" in err
    finally:
        holder.kill()
        holder.wait()
    # A holder that died leaves no lock behind.
    assert record.running(tmp_path / "out") is None
    assert run_cli(capsys, "run", str(path))[0] == 0


@pytest.mark.slow
def test_two_runs_started_together_on_one_folder_never_print_each_others_numbers(tmp_path, root):
    """Run A (the real notebooks, in a second process) and, while it runs, run B on the same
    folder with every label flipped: B is refused, A prints its own AP."""
    a = params_file(tmp_path, "a.yaml", PAIRS)
    b = params_file(tmp_path, "b.yaml", FLIPPED)
    env = {**os.environ, "PYTHONPATH": str(config.PROJECT_ROOT)}
    first = subprocess.Popen(
        [sys.executable, "-m", "gvbench_nb", "run", str(a)], stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=env
    )
    deadline = time.monotonic() + 120
    while record.running(tmp_path / "out") is None and first.poll() is None and time.monotonic() < deadline:
        time.sleep(0.05)
    assert record.running(tmp_path / "out") is not None, "run A never held the folder"
    # A stays paused, holding the folder, while B runs: on a loaded machine B's checks could
    # otherwise outlast A's whole run.
    first.send_signal(signal.SIGSTOP)
    try:
        second = subprocess.run(
            [sys.executable, "-m", "gvbench_nb", "run", str(b)], capture_output=True, text=True, env=env, timeout=300
        )
    finally:
        first.send_signal(signal.SIGCONT)
    out, err = first.communicate(timeout=600)
    assert first.returncode == 0, err.decode()[-2000:]
    assert second.returncode == 2 and "another run is writing" in second.stderr
    table = pd.read_csv(tmp_path / "out" / "orb-nn" / "pairs.csv")
    assert table["label"].tolist() == [p.label for p in PAIRS]  # A's labels, not B's
    alone = evaluate_scores(table["label"].to_numpy(), table["score"].to_numpy())
    printed = next(line.split() for line in out.decode().splitlines() if line.startswith("orb-nn"))
    assert float(printed[4]) == pytest.approx(alone["ap"], abs=1e-6)  # A prints its own AP


# ------------------------------------------------------------------ bindings --
def test_a_run_on_another_pair_file_into_a_folder_holding_other_methods_is_refused(
    tmp_path, root, capsys, notebooks_here
):
    assert run_cli(capsys, "run", str(params_file(tmp_path)))[0] == 0
    before = snapshot(tmp_path / "out")
    flipped = params_file(tmp_path, "flipped.yaml", FLIPPED, methods=["sift-opencv-nn"])
    code, _, err = run_cli(capsys, "run", str(flipped))
    assert code == 2 and "holds results of orb-nn computed on other pairs, labels or images" in one_sentence(err)
    assert "--methods sift-opencv-nn,orb-nn" in err
    assert snapshot(tmp_path / "out") == before
    # Rerunning every method of the folder on the new file replaces them all.
    assert run_cli(capsys, "run", str(flipped), "--methods", "sift-opencv-nn,orb-nn")[0] == 0
    results = pd.read_csv(tmp_path / "out" / "results.csv")
    assert sorted(results["method"]) == ["orb-nn", "sift-opencv-nn"] and results["pairs_digest"].nunique() == 1


def test_results_and_the_report_refuse_methods_scored_on_different_labels_naming_them(tmp_path, root, capsys):
    out, cache, tables = tmp_path / "out", tmp_path / "cache", {}
    for method, pairs in (("orb-nn", PAIRS), ("sift-opencv-nn", FLIPPED)):  # the library writes in place
        tables[method] = method_runs.run_method(
            Sequence("photos", root, pairs), method, "repository", out, cache, device="cpu", progress=False
        )
    code, out_text, err = run_cli(capsys, "results", str(out))
    assert code == 2 and out_text == ""
    assert "scored on different pairs or labels (orb-nn: pairs" in one_sentence(err) and "sift-opencv-nn: pairs" in err
    with pytest.raises(method_outputs.ResultsError, match="label 4 of the same pairs differently"):
        run_tables.align_tables(tables)  # the report never scores one method against another's labels
    # The explore notebook's reader refuses them too, and reads one method alone.
    with pytest.raises(method_outputs.ResultsError, match="scored on different pairs or labels"):
        run_tables.load_pairs_tables(out)
    assert list(run_tables.load_pairs_tables(out, ["orb-nn"])) == ["orb-nn"]


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


# ------------------------------------------------------------ published whole --
@pytest.mark.parametrize("failing", ["02_verify.ipynb", "03_evaluate.ipynb"])
def test_a_failed_rerun_leaves_the_folder_as_the_last_good_run_published_it(
    tmp_path, root, capsys, monkeypatch, failing
):
    monkeypatch.setattr(run_and_publish, "execute_notebook", in_process_notebooks)
    path = params_file(tmp_path)
    assert run_cli(capsys, "run", str(path))[0] == 0
    before = published_files(tmp_path / "out")

    def fails_in(name, output_path, parameters):
        if name == failing:
            output_path.write_text("the executed notebook, with its traceback")
            raise RuntimeError(f"{name} failed")
        in_process_notebooks(name, output_path, parameters)

    monkeypatch.setattr(run_and_publish, "execute_notebook", fails_in)
    with pytest.raises(RuntimeError, match="failed"):
        cli.main(["run", str(path)])
    err = capsys.readouterr().err
    stage = next(p for p in (tmp_path / "out").iterdir() if p.name.startswith(record.STAGE_PREFIX))
    assert f"this run's partial work and executed notebooks are in {stage}" in err
    assert (stage / failing.replace(".ipynb", "_orb-nn.ipynb" if "02" in failing else ".ipynb")).is_file()
    assert published_files(tmp_path / "out") == before
    assert run_cli(capsys, "results", str(tmp_path / "out"))[0] == 0
    # The next good run clears the failed run's stage.
    monkeypatch.setattr(run_and_publish, "execute_notebook", in_process_notebooks)
    assert run_cli(capsys, "run", str(path))[0] == 0
    assert not stage.exists()


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


def test_a_publication_killed_half_way_is_finished_by_the_next_reader_or_run(
    tmp_path, root, capsys, monkeypatch, notebooks_here
):
    path = params_file(tmp_path)
    moved: list[str] = []
    real_replace = os.replace

    def killed_after_two(source, target):
        stage = str(tmp_path / "out" / record.STAGE_PREFIX)
        if str(source).startswith(stage) and not str(target).startswith(stage):  # publishing, not staging
            if len(moved) == 2:
                raise KeyboardInterrupt  # as a kill between two moves would stop it
            moved.append(str(target))
        real_replace(source, target)

    monkeypatch.setattr(record.os, "replace", killed_after_two)
    assert cli.main(["run", str(path)]) == 130  # interrupted
    monkeypatch.setattr(record.os, "replace", real_replace)
    # No run holds the folder any more: its first reader finishes the move and shows the run whole.
    code, out, _ = run_cli(capsys, "results", str(tmp_path / "out"))
    assert code == 0 and "orb-nn" in out and record.read_record(tmp_path / "out")["state"] == "published"
    assert run_cli(capsys, "run", str(path))[0] == 0


# ---------------------------------------------------------------- the table --
def test_the_folder_table_lists_every_method_run_one_at_a_time(tmp_path, root, capsys, notebooks_here):
    path = params_file(tmp_path)
    assert run_cli(capsys, "run", str(path), "--methods", "orb-nn")[0] == 0
    code, out, _ = run_cli(capsys, "run", str(path), "--methods", "sift-opencv-nn")
    assert code == 0
    results = pd.read_csv(tmp_path / "out" / "results.csv")
    assert sorted(results["method"]) == ["orb-nn", "sift-opencv-nn"]
    assert "orb-nn" in out and "sift-opencv-nn" in out  # the table `run` prints is the folder's
    kept = json.loads((tmp_path / "out" / "orb-nn" / "run.json").read_text())
    assert kept["binding"]["pairs_digest"] == scoring.pairs_digest((p.query, p.reference, p.label) for p in PAIRS)


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

    class OneSecond(datetime.datetime):  # both stages opened in the same second, whatever the load
        @classmethod
        def now(cls, tz=None):
            return datetime.datetime(2026, 12, 4, 12, 0, 0, tzinfo=tz)

    monkeypatch.setattr(datetime, "datetime", OneSecond)
    first = record.stage_run_id(record.open_stage(tmp_path))
    second = record.stage_run_id(record.open_stage(tmp_path))
    assert first.split("-")[0] == second.split("-")[0] == "20261204T120000Z" and first != second


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


# -------------------------------------------------------------- interruption --
@pytest.mark.slow
def test_ctrl_c_during_a_run_keeps_the_published_results(tmp_path, root):
    path = params_file(tmp_path)
    env = {**os.environ, "PYTHONPATH": str(config.PROJECT_ROOT)}
    subprocess.run([sys.executable, "-m", "gvbench_nb", "run", str(path)], check=True, env=env, capture_output=True)
    before = published_files(tmp_path / "out")
    second = subprocess.Popen(
        [sys.executable, "-m", "gvbench_nb", "run", str(path), "--methods", "orb-nn,sift-opencv-nn"],
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
    )
    deadline = time.monotonic() + 120
    while (
        not list((tmp_path / "out").glob(f"{record.STAGE_PREFIX}*/01_sequence.ipynb")) and time.monotonic() < deadline
    ):
        time.sleep(0.05)
    second.send_signal(signal.SIGINT)
    second.communicate(timeout=120)
    assert second.returncode != 0
    assert published_files(tmp_path / "out") == before
