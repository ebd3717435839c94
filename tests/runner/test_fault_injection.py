"""Fault injection: no change of input leaves a stale result, and every user error is one sentence.
Four small photographs (scikit-image's) and their warped copies, matched with SIFT: seconds."""

from __future__ import annotations

import hashlib
import json
import os
import re
import shutil
from pathlib import Path

import cv2
import h5py
import numpy as np
import pandas as pd
import pytest
import yaml
from helpers import PAIRS, check_stage_outputs, cli_error, photo, write_params, write_root

from gvbench_nb import cli, methods, notebook, run_and_publish
from gvbench_nb.data.sequences import Pair, Sequence, frame_tolerance_pairs, read_pairs, write_pairs
from gvbench_nb.protocol.images import ImageReadError
from gvbench_nb.runner import (
    config,
    image_features,
    method_outputs,
    method_runs,
    pair_matching,
    runs,
    scoring,
    sequence_build,
)
from gvbench_nb.runner import store as store_module
from gvbench_nb.runner.store import ShardedStore, StoreCorruptError

pytestmark = pytest.mark.reliability

METHOD, PROFILE = "sift-nn", "paper"
SCORE_COLUMNS = ["query", "reference", "label", "num_keypoints_query", "num_keypoints_reference"]
SCORE_COLUMNS += ["num_matches", "num_inliers", "score"]


def run(root: Path, work: Path, pairs: list[Pair] = PAIRS, seed: int = 0) -> pd.DataFrame:
    sequence = Sequence("photos", root, list(pairs))
    return method_runs.run_method(
        sequence, METHOD, PROFILE, work / "out", work / "cache", device="cpu", seed=seed, progress=False, threads=1
    )


def method_dir(output_dir: Path) -> Path:
    """The folder of METHOD's results the output folder shows (its current run's)."""
    return method_outputs.method_dir(output_dir, METHOD)


def this_run(work: Path) -> dict:
    return json.loads((method_dir(work / "out") / "run.json").read_text())["this_run"]


# ------------------------------------------------------- 1, 2: content-keyed caches --
def test_an_image_replaced_in_place_is_extracted_and_matched_again(root, tmp_path):
    first = run(root, tmp_path / "work")
    other = photo("chelsea", warped=True)
    cv2.imwrite(str(root / "query" / "a.png"), other)  # another photo, same name
    second = run(root, tmp_path / "work")
    fresh = run(root, tmp_path / "fresh")
    pd.testing.assert_frame_equal(second[SCORE_COLUMNS], fresh[SCORE_COLUMNS])
    assert not first[SCORE_COLUMNS].equals(second[SCORE_COLUMNS])
    # Exactly what the change invalidates: one image, the two pairs that use it.
    assert this_run(tmp_path / "work")["extraction"] == {"images": 4, "cached": 3, "extracted": 1}
    assert this_run(tmp_path / "work")["matching"] == {"pairs": 4, "cached": 2, "matched": 2}


def test_another_image_root_with_the_same_output_dir_recomputes_every_score(root, tmp_path):
    other = write_root(tmp_path / "other_images", photos=("chelsea", "rocket"))
    run(root, tmp_path / "work")
    switched = run(other, tmp_path / "work")
    fresh = run(other, tmp_path / "fresh")
    pd.testing.assert_frame_equal(switched[SCORE_COLUMNS], fresh[SCORE_COLUMNS])
    assert this_run(tmp_path / "work")["matching"]["matched"] == 4


def test_an_identical_copy_of_the_images_elsewhere_reuses_the_caches(root, tmp_path):
    first = run(root, tmp_path / "work")
    copy = shutil.copytree(root, tmp_path / "copy")
    again = run(copy, tmp_path / "work")
    pd.testing.assert_frame_equal(first[SCORE_COLUMNS], again[SCORE_COLUMNS])
    done = this_run(tmp_path / "work")
    assert done["extraction"]["extracted"] == done["matching"]["matched"] == 0


def test_another_seed_is_verified_again(root, tmp_path):
    run(root, tmp_path / "work", seed=0)
    run(root, tmp_path / "work", seed=1)
    assert this_run(tmp_path / "work")["matching"]["matched"] == 4
    assert this_run(tmp_path / "work")["extraction"]["extracted"] == 0  # features do not depend on it


def test_content_keys_follow_the_bytes_not_the_name(root, tmp_path):
    key = image_features.image_key(root, "query/a.png")
    assert key == image_features.content_key(root / "query" / "a.png")
    assert key.startswith("blake2b-") and str(root) not in key
    assert image_features.image_key(shutil.copytree(root, tmp_path / "copy"), "query/a.png") == key
    (root / "query" / "a.png").write_bytes((root / "query" / "b.png").read_bytes())
    assert image_features.image_key(root, "query/a.png") != key
    with pytest.raises(ImageReadError, match="image not found: .*missing.png; check image_root"):
        image_features.image_key(root, "missing.png")


# ----------------------------------------- 3: builder-built pair files and run.json --
def _frame_root(root: Path) -> Path:
    for folder in ("night", "day"):
        (root / folder).mkdir(parents=True)
        for frame in range(60):
            (root / folder / f"Image{frame:03d}.png").write_bytes(b"")  # the builder reads names only
    return root


def test_a_builder_pair_file_is_rebuilt_when_its_options_or_seed_change(tmp_path):
    _frame_root(tmp_path / "images")
    options = {"query_folder": "night", "reference_folder": "day", "candidates_per_query": 10}

    def build(seed: int = 0, **option_changes) -> Sequence:
        path = write_params(
            tmp_path, pairs_builder="frame_tolerance", builder_options={**options, **option_changes}, seed=seed
        )
        return sequence_build.prepare_sequence(config.load_params(path))

    def expected(candidates_per_query: int) -> int:
        names = [f"Image{frame:03d}.png" for frame in range(60)]
        night, day = [f"night/{n}" for n in names], [f"day/{n}" for n in names]
        return len(frame_tolerance_pairs(night, day, candidates_per_query=candidates_per_query))

    assert len(build().pairs) == expected(10) > len(build(candidates_per_query=4).pairs) == expected(4)
    first_seed = build(seed=0).pairs
    assert build(seed=1).pairs != first_seed and build(seed=0).pairs == first_seed
    sequence = build()
    pairs_file = tmp_path / "pairs.txt"
    assert sequence.origin["pairs_sha256"] == hashlib.sha256(pairs_file.read_bytes()).hexdigest()
    assert sequence.origin["builder_options"] == options and sequence.origin["pairs_builder"] == "frame_tolerance"
    # A builder's file edited by hand is its builder's again at the next run.
    pairs_file.write_text("night/Image000.png day/Image001.png 1\n")
    assert len(build().pairs) == expected(10)


def test_run_json_records_the_pair_file_hash_builder_options_and_image_root(root, tmp_path):
    pairs_file = write_pairs(tmp_path / "pairs.txt", PAIRS)
    params = config.load_params(write_params(tmp_path, image_root=str(root)))
    sequence = sequence_build.prepare_sequence(params)
    method_runs.run_method_of_params({**params, "device": "cpu"}, sequence, METHOD, progress=False, threads=1)
    recorded = json.loads((method_dir(Path(params["output_dir"])) / "run.json").read_text())
    assert recorded["pairs"]["pairs_sha256"] == hashlib.sha256(pairs_file.read_bytes()).hexdigest()
    assert recorded["pairs"]["pairs_file"] == str(pairs_file)
    assert recorded["pairs"]["builder_options"] == {} and recorded["pairs"]["pairs_builder"] is None
    assert recorded["image_root"] == str(root) and recorded["seed"] == params["seed"]


# ------------------------------------------------------ 4, 5: a run owns its outputs --
def test_cli_overrides_reach_every_notebook_through_one_resolved_params_file(root, tmp_path, monkeypatch):
    write_pairs(tmp_path / "pairs.txt", PAIRS)
    params_path = write_params(tmp_path, image_root=None)  # as the official lists ship: no image root
    seen: list[dict] = []

    def fake_execute(name, output_path, parameters):  # what each notebook's first cell loads
        loaded = notebook.load_params(parameters["params_file"], profile=parameters.get("profile"))
        written = all((output_path.parent / METHOD / f).is_file() for f in ("pairs.csv", "run.json"))
        keys = ("image_root", "limit", "profile", "output_dir")
        seen.append({"notebook": name, "result_written": written, **{k: loaded[k] for k in keys}})
        if name == "03_evaluate.ipynb":
            output_path.parent.mkdir(parents=True, exist_ok=True)
            row = {"method": METHOD, "profile": "repository", "n_pairs": 3, "n_positives": 2, "ap": 1.0}
            pd.DataFrame([{**row, "max_recall": 1.0, "seconds_per_pair": 0.0, "timers": "this run"}]).to_csv(
                output_path.parent / "results.csv"
            )

    monkeypatch.setattr(run_and_publish, "execute_notebook", fake_execute)
    out = tmp_path / "elsewhere"
    argv = ["run", str(params_path), "--image-root", str(root), "--limit", "3", "--profile", "repository"]
    assert cli.main([*argv, "--output-dir", str(out)]) == 0
    # 01_sequence runs beside the others; 02_verify and 03_evaluate once the method's result is
    # written (in either order: 03_evaluate reads the result, not the 02_verify notebook).
    by_notebook = {s.pop("notebook"): s for s in seen}
    assert sorted(by_notebook) == ["01_sequence.ipynb", "02_verify.ipynb", "03_evaluate.ipynb"]
    assert by_notebook["02_verify.ipynb"]["result_written"] and by_notebook["03_evaluate.ipynb"]["result_written"]
    assert all(s == {**s, "image_root": str(root), "limit": 3, "profile": "repository"} for s in seen)
    # The notebooks write into the run being built inside the output folder; the run's params name the folder.
    building = {Path(s["output_dir"]) for s in seen}
    assert building == {out / runs.RUNS / f"{runs.BUILDING}{runs.run_id(next(iter(building)))}"}
    published = yaml.safe_load(runs.resolved_params(out).read_text())
    assert published["image_root"] == str(root) and published["output_dir"] == str(out)


@pytest.mark.slow
def test_image_root_given_on_the_command_line_reaches_the_real_notebooks(root, tmp_path):
    """The README's `run params/night.yaml --image-root /path`, through papermill."""
    import subprocess
    import sys

    write_pairs(tmp_path / "pairs.txt", PAIRS)
    params_path = write_params(tmp_path, image_root=None)
    done = subprocess.run(
        [sys.executable, "-m", "gvbench_nb", "run", str(params_path), "--image-root", str(root)],
        capture_output=True,
        text=True,
        timeout=600,
        cwd=tmp_path,
        env={**os.environ, "GVBENCH_THREADS": "1"},
    )
    assert done.returncode == 0, done.stderr[-2000:]
    results = pd.read_csv(tmp_path / "out" / "results.csv")
    assert list(results["method"]) == [METHOD]
    check_stage_outputs(tmp_path / "out", METHOD, PAIRS)  # one row a pair, metrics recomputed from them
    assert json.loads((method_dir(tmp_path / "out") / "run.json").read_text())["image_root"] == str(root)


def test_the_stage_notebooks_load_the_params_file_they_are_given():
    from gvbench_nb.reporting.execute import NOTEBOOKS_DIR

    notebooks = Path(NOTEBOOKS_DIR)
    for name in ("01_sequence.ipynb", "02_verify.ipynb", "03_evaluate.ipynb"):
        source = "\n".join("".join(cell["source"]) for cell in json.loads((notebooks / name).read_text())["cells"])
        assert re.search(r"\b(notebook\.load_params|notebook\.load_sequence)\(\s*params_file\b", source), name


def stage_jobs(methods: str) -> list[tuple[str, str, dict]]:
    """The run's notebooks: 01_sequence, one 02_verify a method (one letter each), 03_evaluate."""
    verify = [("02_verify.ipynb", f"02_verify_{m}.ipynb", {"method": m}) for m in methods]
    return [("01_sequence.ipynb", "01_sequence.ipynb", {}), *verify, ("03_evaluate.ipynb", "03_evaluate.ipynb", {})]


def test_a_method_that_fails_in_the_command_fails_in_its_notebook_and_stops_the_run(tmp_path, monkeypatch):
    """The notebook of the method whose work failed runs it again (from the caches) and keeps
    the traceback; the methods after it are not started and nothing is evaluated."""
    executed, computed = [], []

    def fake_execute(name, output_path, parameters):
        executed.append(output_path.name)
        if output_path.name == "02_verify_b.ipynb":
            raise RuntimeError("b failed in its notebook too")

    def compute(method):
        computed.append(method)
        if method == "b":
            raise RuntimeError("b failed")

    monkeypatch.setattr(run_and_publish, "execute_notebook", fake_execute)
    with pytest.raises(RuntimeError, match="in its notebook too"):
        run_and_publish.execute_run_notebooks(stage_jobs("abc"), tmp_path, compute)
    assert computed == ["a", "b"]
    assert sorted(executed) == ["01_sequence.ipynb", "02_verify_a.ipynb", "02_verify_b.ipynb"]


def test_evaluate_waits_for_every_verify_notebook_but_not_for_the_sequence_notebook(tmp_path, monkeypatch):
    import threading

    sequence_may_finish, events = threading.Event(), []

    def fake_execute(name, output_path, parameters):
        if output_path.name == "01_sequence.ipynb":
            assert sequence_may_finish.wait(30)
        events.append(output_path.name)
        if output_path.name == "03_evaluate.ipynb":
            sequence_may_finish.set()

    monkeypatch.setattr(run_and_publish, "execute_notebook", fake_execute)
    run_and_publish.execute_run_notebooks(stage_jobs("ab"), tmp_path, lambda method: None)
    assert events[-2:] == ["03_evaluate.ipynb", "01_sequence.ipynb"]
    assert sorted(events[:2]) == ["02_verify_a.ipynb", "02_verify_b.ipynb"]


def test_a_run_that_fails_leaves_the_previous_results_whole_and_says_where_its_work_is(
    root, tmp_path, monkeypatch, capsys
):
    write_pairs(tmp_path / "pairs.txt", PAIRS)
    params_path = write_params(tmp_path, image_root=str(root), cache_dir=str(tmp_path / "work" / "cache"))
    out = tmp_path / "work" / "out"
    run_first = run(root, tmp_path / "work")  # an earlier finished run in the same folder
    scoring.evaluate(out)
    before = {p: p.read_bytes() for p in [*(out / runs.RUNS).rglob("*"), out / "results.csv"] if p.is_file()}
    assert len(run_first) == 4

    def kernel_dies(name, output_path, parameters):
        raise RuntimeError("the kernel died")

    monkeypatch.setattr(run_and_publish, "execute_notebook", kernel_dies)
    capsys.readouterr()
    with pytest.raises(RuntimeError, match="kernel died"):
        cli.main(["run", str(params_path), "--output-dir", str(out)])
    said = capsys.readouterr().err
    assert f"{out} shows what it showed before" in said
    aside = list((out / runs.RUNS).glob(f"{runs.BUILDING}*"))
    assert len(aside) == 1 and str(aside[0]) in said
    assert {p: p.read_bytes() for p in before} == before and len(runs.finished_runs(out)) == 1
    assert cli.main(["results", str(out)]) == 0


# ------------------------------------------------------------- 6: verified stores --
def _dataset_offset(shard: Path, name: str) -> tuple[int, int]:
    """Where in the shard's file the first entry's array ``name`` lies: (offset, size) in bytes."""
    with h5py.File(shard, "r") as handle:
        table = json.loads(bytes(handle[store_module._ENTRIES][()]))
        start = handle[store_module._DATA].id.get_offset()
    for entry in table.values():
        if name in entry["arrays"]:
            offset, dtype, shape, _ = entry["arrays"][name]
            return start + offset, int(np.prod(shape)) * np.dtype(dtype).itemsize
    raise AssertionError(f"no array {name} in {shard}")


def test_bytes_overwritten_inside_a_feature_shard_raise_store_corrupt_naming_it(root, tmp_path):
    run(root, tmp_path / "work")
    store = image_features.feature_store(tmp_path / "work" / "cache", methods.resolve_method(METHOD)["extractor"])
    shard = store.shards()[0]
    offset, size = _dataset_offset(shard, "keypoints")
    data = bytearray(shard.read_bytes())
    data[offset + size // 2 : offset + size // 2 + 16] = bytes(16)  # same file size, keypoints changed
    shard.write_bytes(bytes(data))
    with pytest.raises(StoreCorruptError) as error:
        run(root, tmp_path / "work")
    assert f"shard {shard}" in str(error.value) and "'keypoints'" in str(error.value)
    assert "Delete that file" in str(error.value)


def test_an_attribute_changed_inside_a_match_shard_is_detected(root, tmp_path):
    run(root, tmp_path / "work")
    store = pair_matching.match_store(tmp_path / "work" / "cache", methods.resolve_method(METHOD))
    shard = store.shards()[0]
    with h5py.File(shard, "r+") as handle:  # a tool "fixing" an inlier count in place
        table = json.loads(bytes(handle[store_module._ENTRIES][()]))
        entry = next(iter(table.values()))
        entry["attrs"]["num_inliers"] += 5
        del handle[store_module._ENTRIES]
        handle.create_dataset(store_module._ENTRIES, data=np.void(json.dumps(table).encode()))
    with pytest.raises(StoreCorruptError, match="entries table does not match its checksum"):
        run(root, tmp_path / "work")


def test_every_dataset_and_attribute_of_an_entry_is_checked(tmp_path):
    store = ShardedStore(tmp_path / "s")
    with store.writer() as writer:
        writer.put(
            "k",
            {"x": np.arange(6, dtype=np.float32).reshape(3, 2), "empty": np.zeros((0, 2)), "scalar": np.int64(7)},
            {"num_inliers": 13, "name": "a"},
        )
    entry = ShardedStore(tmp_path / "s").read("k")
    assert entry["attr:num_inliers"] == 13 and entry["scalar"] == 7 and entry["empty"].shape == (0, 2)
    assert not any(name.startswith("attr:_digest") for name in entry)
    offset, size = _dataset_offset(store.shards()[0], "x")
    data = bytearray(store.shards()[0].read_bytes())
    data[offset] ^= 0xFF  # one byte of x
    store.shards()[0].write_bytes(bytes(data))
    with pytest.raises(StoreCorruptError, match="array 'x' of entry 'k' does not match its checksum"):
        ShardedStore(tmp_path / "s").read("k")
    assert ShardedStore(tmp_path / "s").read("k", fields=("empty",))["empty"].shape == (0, 2)


# ------------------------------------------------------ 7: pairs are identities --


def test_a_name_with_spaces_runs_end_to_end(root, tmp_path):
    (root / "query" / "a.png").rename(root / "query" / "a copy.png")
    path = write_pairs(
        tmp_path / "pairs.txt",
        [Pair("query/a copy.png", "reference/a.png", 1), Pair("query/a copy.png", "reference/b.png", 0)],
    )
    table = run(root, tmp_path / "work", read_pairs(path))
    assert list(table["query"]) == ["query/a copy.png"] * 2 and table["num_inliers"].iloc[0] > 0


def test_a_symlink_leaving_the_image_root_is_followed_as_documented(root, tmp_path):
    outside = tmp_path / "outside"
    outside.mkdir()
    shutil.move(str(root / "reference" / "b.png"), outside / "b.png")
    (root / "reference" / "b.png").symlink_to(outside / "b.png")
    linked = run(root, tmp_path / "work")
    fresh = run(write_root(tmp_path / "plain"), tmp_path / "fresh")
    pd.testing.assert_frame_equal(linked[SCORE_COLUMNS], fresh[SCORE_COLUMNS])


# ----------------------------------------------------- errors are one sentence --
@pytest.fixture
def valid(root, tmp_path) -> Path:
    write_pairs(tmp_path / "pairs.txt", PAIRS)
    return write_params(tmp_path, image_root=str(root))


@pytest.mark.parametrize("case", ["pair file missing", "output_dir a file", "not writable", "no results", "no root"])
def test_a_user_error_is_one_sentence(tmp_path, capsys, valid, case):
    out, nowhere, argv = tmp_path / "out", tmp_path / "nowhere", ["run", str(valid)]
    if case == "pair file missing":
        (tmp_path / "pairs.txt").unlink()
        expected = [f"{valid}: the pair file {tmp_path / 'pairs.txt'} does not exist; set pairs"]
    elif case == "output_dir a file":
        out.write_text("")
        expected = [f"output_dir {out} is a file, not a folder; set output_dir (or pass --output-dir)"]
    elif case == "not writable":  # root writes anywhere a mode allows nothing; /proc refuses even root
        target = Path("/proc/gvbench-nb-not-writable") if os.geteuid() == 0 else nowhere
        if os.geteuid() != 0:
            target.mkdir(mode=0o500)
        argv += ["--output-dir", str(target)]
        expected = [f"cannot write in output_dir {target}", "--output-dir"]
    elif case == "no results":
        nowhere.mkdir()
        argv = ["results", str(nowhere)]
        expected = [f"{nowhere} holds no method results"]
    else:
        argv += ["--image-root", str(nowhere)]
        expected = [f"image_root {nowhere} does not exist", "--image-root"]
    message = cli_error(capsys, *argv)
    assert all(part in message for part in expected), message


def test_an_image_deleted_since_the_last_run_names_it_and_its_pair(tmp_path, capsys, valid, root):
    (root / "reference" / "b.png").unlink()
    message = cli_error(capsys, "run", str(valid))
    assert "1 of 4 images of sequence 's' are missing" in message
    assert "first reference/b.png (pair 1: query/a.png reference/b.png" in message
    with pytest.raises(ImageReadError, match=r"reference/b.png.*pair 1: query/a.png reference/b.png"):
        run(root, tmp_path / "work")


def test_a_params_path_that_is_a_folder_says_so(tmp_path, capsys):
    (tmp_path / "params").mkdir()
    (tmp_path / "params" / "mine.yaml").write_text("{}")
    message = cli_error(capsys, "run", str(tmp_path / "params"))
    assert f"params path {tmp_path / 'params'} is a folder, not a params file" in message
    assert str(tmp_path / "params" / "mine.yaml") in message
    with pytest.raises(config.ParamsError, match="is a folder"):  # --debug: the traceback instead
        cli.main(["--debug", "run", str(tmp_path / "params")])


def test_a_negative_limit_is_blamed_on_the_option(valid, capsys):
    with pytest.raises(SystemExit) as exit_code:
        cli.main(["run", str(valid), "--limit", "-3"])
    assert exit_code.value.code == 2
    message = capsys.readouterr().err
    assert "argument --limit: must be a positive whole number of pairs, got '-3'" in message
    assert str(valid) not in message
