"""Reliability on Gardens Point frames at 320x180 with ``sift-nn``: interrupted runs lose nothing,
concurrent runs corrupt nothing, the same input gives the same scores. Kills are real SIGKILLs a
child (``CHILD``) sends itself at the n-th stored item, so the library holds no fault injection."""

from __future__ import annotations

import csv
import io
import json
import os
import re
import shutil
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import pandas as pd
import pytest
import torch
from helpers import truncated

from gvbench_nb import methods
from gvbench_nb.data.sequences import Pair, Sequence
from gvbench_nb.protocol.images import ImageReadError
from gvbench_nb.protocol.metrics import MetricsUndefinedError
from gvbench_nb.runner import (
    concurrency,
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

METHOD = "sift-nn"
PROFILE = "paper"
FRAMES = list(range(0, 200, 10))  # 20 queries, 20 references -> 40 images
N_PAIRS = 4 * len(FRAMES)  # 80 pairs: 20 true, 60 false
EXTRACT_FLUSH, MATCH_FLUSH = 16, 64  # pipeline's shard sizes: kills are placed past one commit
SCORES = ["query", "reference", "label", "num_matches", "num_matches_filtered", "num_inliers", "score"]


# ---------------------------------------------------------------- fixtures --
def frame_pairs() -> list[Pair]:
    """Each query with its own frame (true) and three frames 10-100 away (false)."""
    pairs = []
    for q in FRAMES:
        for offset in (0, 10, 20, 100):
            r = (q + offset) % 200
            pairs.append(Pair(f"night_right/Image{q:03d}.jpg", f"day_right/Image{r:03d}.jpg", int(offset == 0)))
    return pairs


def one_thread(n_threads: int | None = None, jobs: int = 1) -> int:
    """Stand-in for ``concurrency.configure_threads``: on tiny images (and a shared, busy
    machine) one thread is about twice as fast as all cores; scores do not change."""
    torch.set_num_threads(1)
    cv2.setNumThreads(1)
    return 1


@pytest.fixture(scope="module", autouse=True)
def single_thread():
    threads = torch.get_num_threads()
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(concurrency, "configure_threads", one_thread)
        yield
    torch.set_num_threads(threads)


@pytest.fixture(scope="module")
def small_root(shared_data, tmp_path_factory) -> Path:
    """Gardens Point frames downscaled 3x into a scratch image root."""
    root = tmp_path_factory.mktemp("gp_small")
    for folder in ("night_right", "day_right"):
        (root / folder).mkdir()
        for frame in FRAMES:
            image = cv2.imread(str(shared_data / "gardens_point" / folder / f"Image{frame:03d}.jpg"))
            small = cv2.resize(image, (320, 180), interpolation=cv2.INTER_AREA)
            cv2.imwrite(str(root / folder / f"Image{frame:03d}.jpg"), small, [cv2.IMWRITE_JPEG_QUALITY, 95])
    return root


@pytest.fixture(scope="module")
def sequence(small_root) -> Sequence:
    return Sequence("gp_small", small_root, frame_pairs())


@pytest.fixture(scope="module")
def baseline(single_thread, sequence, tmp_path_factory) -> dict[str, Path]:
    """One uninterrupted run from scratch: what every other run must reproduce."""
    base = tmp_path_factory.mktemp("baseline")
    run_here(sequence, base, jobs=1)
    return {"out": base / "out", "cache": base / "cache"}


CHILD = r"""
import json, os, signal, sys
from pathlib import Path

spec = json.loads(Path(sys.argv[1]).read_text())
from gvbench_nb.runner import store
from gvbench_nb.runner import concurrency, image_features, method_outputs, method_runs, pair_matching, scoring
from gvbench_nb.data.sequences import Pair, Sequence

def one_thread(n_threads=None, jobs=1):  # as the tests' in-process runs (speed only)
    import cv2, torch
    torch.set_num_threads(1)
    cv2.setNumThreads(1)
    return 1

concurrency.configure_threads = one_thread
stage, _, count = (spec.get("kill") or "").partition(":")
seen = [0]

def die():
    sys.stdout.flush()
    os.kill(os.getpid(), signal.SIGKILL)

if stage in ("extract", "match"):
    put = store.ShardWriter.put
    def counting_put(self, key, arrays, attrs=None):
        if (self.store.folder.parent.name == "features") == (stage == "extract"):
            seen[0] += 1
            if seen[0] > int(count):
                die()  # killed while item n+1 is being stored
        put(self, key, arrays, attrs)
    store.ShardWriter.put = counting_put
elif stage == "flush":  # killed while a shard file is being written (two datasets a shard)
    import h5py
    create_dataset = h5py.Group.create_dataset
    def counting_create_dataset(self, name, *args, **kwargs):
        seen[0] += 1
        if seen[0] > int(count):
            die()
        return create_dataset(self, name, *args, **kwargs)
    h5py.Group.create_dataset = counting_create_dataset
elif stage == "write":
    import pandas as pd
    to_csv = pd.DataFrame.to_csv
    def half_to_csv(self, path=None, *args, **kwargs):
        if path is not None and count in Path(path).name:  # the temporary file (or, unsafely, the file)
            text = to_csv(self, None, *args, **kwargs)
            with open(path, "w") as stream:  # the temporary file, half written, on disk
                stream.write(text[: len(text) // 2])
                stream.flush()
                os.fsync(stream.fileno())
            die()
        return to_csv(self, path, *args, **kwargs)
    pd.DataFrame.to_csv = half_to_csv

if spec.get("go_file"):  # start together with another process
    import time
    Path(spec["ready_file"]).touch()
    while not Path(spec["go_file"]).exists():
        time.sleep(0.005)

sequence = Sequence(spec["name"], Path(spec["image_root"]), [Pair(*p) for p in spec["pairs"]])
method_runs.run_method(sequence, spec["method"], spec["profile"], Path(spec["output_dir"]), Path(spec["cache_dir"]),
                    device="cpu", progress=False)
print("finished")
"""


STARTED: list[subprocess.Popen] = []


@pytest.fixture(autouse=True)
def no_child_left_running():
    """A failed test must not leave a child process running (it would write on)."""
    yield
    while STARTED:
        child = STARTED.pop()
        if child.poll() is None:
            child.kill()
            child.wait()


def start_child(
    sequence: Sequence, work: Path, name: str, kill: str | None = None, go_file: Path | None = None
) -> subprocess.Popen:
    spec = {
        "name": sequence.name,
        "image_root": str(sequence.image_root),
        "pairs": [[p.query, p.reference, p.label] for p in sequence.pairs],
        "method": METHOD,
        "profile": PROFILE,
        "output_dir": str(work / "out"),
        "cache_dir": str(work / "cache"),
        "kill": kill,
        "go_file": str(go_file) if go_file else None,
        "ready_file": str(work / f"{name}.ready"),
    }
    spec_path = work / f"{name}.json"
    spec_path.write_text(json.dumps(spec))
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    child = subprocess.Popen(
        [sys.executable, "-c", CHILD, str(spec_path)],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=env,
    )
    STARTED.append(child)
    return child


def run_here(sequence: Sequence, work: Path, cache: Path | None = None, **options) -> pd.DataFrame:
    out, cache = work / "out", cache or work / "cache"
    return method_runs.run_method(sequence, METHOD, PROFILE, out, cache, device="cpu", progress=False, **options)


def run_json(output_dir: Path) -> dict:
    return json.loads((method_outputs.method_dir(output_dir, METHOD) / "run.json").read_text())


def rows_without_timings(path: Path) -> list[list[str]]:
    """pairs.csv as exact text fields, minus the ``*_seconds`` columns (measurements)."""
    rows = list(csv.reader(io.StringIO(path.read_text())))
    keep = [i for i, column in enumerate(rows[0]) if not column.endswith("_seconds")]
    assert len(keep) == len(rows[0]) - 3, rows[0]
    return [[row[i] for i in keep] for row in rows]


def assert_same_pairs(output_dir: Path, baseline_out: Path) -> None:
    produced = rows_without_timings(method_outputs.method_dir(output_dir, METHOD) / "pairs.csv")
    expected = rows_without_timings(method_outputs.method_dir(baseline_out, METHOD) / "pairs.csv")
    assert len(produced) == N_PAIRS + 1
    assert produced == expected


def store_entries(store: ShardedStore) -> dict[str, list[dict[str, np.ndarray]]]:
    """Every copy of every entry, read shard by shard (duplicates from concurrent writers too)."""
    entries: dict[str, list[dict[str, np.ndarray]]] = {}
    for shard in store.shards():
        one = ShardedStore(store.folder)
        one._index = dict.fromkeys(one._opened(shard)[1], shard)  # this shard's copy of each key
        for key in one._index:
            entry = one.read(key)
            # Timers differ between runs.
            entries.setdefault(key, []).append({k: v for k, v in entry.items() if not k.endswith("seconds")})
        one.close()
    return entries


def assert_store_matches(store: ShardedStore, reference: ShardedStore) -> None:
    expected = {key: copies[0] for key, copies in store_entries(reference).items()}
    found = store_entries(store)
    assert sorted(found) == sorted(expected)
    for key, copies in found.items():
        for entry in copies:
            assert sorted(entry) == sorted(expected[key]), key
            for name, value in entry.items():
                np.testing.assert_array_equal(value, expected[key][name], err_msg=f"{key} {name}")


def stores(work: Path) -> tuple[ShardedStore, ShardedStore]:
    conf = methods.resolve_method(METHOD, PROFILE)
    return image_features.feature_store(work / "cache", conf["extractor"]), pair_matching.match_store(
        work / "cache", conf
    )


# -------------------------------------------------------- 1. bad input, clear error --
@pytest.mark.real_data
@pytest.mark.parametrize("jobs", ["1", "2"])
def test_a_run_hitting_a_bad_image_names_it_and_keeps_the_finished_results(small_root, tmp_path, monkeypatch, jobs):
    monkeypatch.setenv("GVBENCH_JOBS", jobs)  # the error surfaces from a worker thread as well
    root = tmp_path / "root"
    shutil.copytree(small_root, root)
    good = [
        Pair("night_right/Image000.jpg", "day_right/Image000.jpg", 1),
        Pair("night_right/Image010.jpg", "day_right/Image000.jpg", 0),
    ]
    out = tmp_path / "out"
    run_here(Sequence("s", root, good), tmp_path)
    finished = (method_outputs.method_dir(out, METHOD) / "pairs.csv").read_bytes()

    broken = root / "day_right" / "Image010.jpg"
    truncated(small_root / "day_right" / "Image010.jpg", broken)
    bad_pair = Pair("night_right/Image020.jpg", "day_right/Image010.jpg", 0)
    bigger = Sequence("s", root, good + [Pair("night_right/Image020.jpg", "day_right/Image000.jpg", 0), bad_pair])
    with pytest.raises(ImageReadError) as error:
        run_here(bigger, tmp_path)
    message = str(error.value)
    assert str(broken) in message and "sequence 's'" in message
    assert "pair 3: night_right/Image020.jpg day_right/Image010.jpg" in message
    # The finished results stay as they were, bound to the pairs they scored; this run wrote nothing.
    assert (method_outputs.method_dir(out, METHOD) / "pairs.csv").read_bytes() == finished
    assert scoring.methods_with_results(out) == [METHOD] and run_json(out)["n_pairs"] == len(good)
    # What was extracted before the error is kept: after the fix only the repaired image is extracted.
    shutil.copy(small_root / "day_right" / "Image010.jpg", broken)
    run_here(bigger, tmp_path)
    assert run_json(out)["this_run"]["extraction"] == {"images": 5, "cached": 4, "extracted": 1}


def _evaluate_with_labels(baseline_out: Path, tmp_path: Path, label: int) -> Path:
    out = tmp_path / f"only_{label}"
    building = runs.start(out, "run")
    (building / METHOD).mkdir()
    table = scoring.load_pairs_table(baseline_out, METHOD)
    table[table["label"] == label].to_csv(building / METHOD / "pairs.csv", index=False)
    shutil.copy(method_outputs.method_dir(baseline_out, METHOD) / "run.json", building / METHOD / "run.json")
    runs.finish(building)
    return out


@pytest.mark.real_data
@pytest.mark.parametrize("label, missing", [(1, "negatives"), (0, "positives")])
def test_a_sequence_without_positives_or_negatives_is_an_error_not_nan(baseline, tmp_path, label, missing):
    out = _evaluate_with_labels(baseline["out"], tmp_path, label)
    with pytest.raises(MetricsUndefinedError, match=f"with no {missing}: AP and MR are undefined") as error:
        scoring.evaluate(out)
    assert str(method_outputs.method_dir(out, METHOD) / "pairs.csv") in str(error.value)
    assert not (out / "results.csv").exists()


# ------------------------------------------------------------- 2. nothing lost --
@pytest.mark.slow
@pytest.mark.real_data
@pytest.mark.parametrize(
    "kill, committed_features, committed_matches, extracted_again, matched_again",
    [
        # killed while storing image 21: 16 images committed in one shard, 4 in the buffer lost
        (f"extract:{EXTRACT_FLUSH + 4}", EXTRACT_FLUSH, 0, 40 - EXTRACT_FLUSH, N_PAIRS),
        # killed while writing the second shard (its arrays, before its entries table): that shard is not read
        ("flush:2", EXTRACT_FLUSH, 0, 40 - EXTRACT_FLUSH, N_PAIRS),
        # killed while storing pair 71: every image and 64 pairs committed
        (f"match:{MATCH_FLUSH + 6}", 40, MATCH_FLUSH, 0, N_PAIRS - MATCH_FLUSH),
        # killed half-way through writing pairs.csv: everything committed, nothing to redo
        ("write:pairs.csv", 40, N_PAIRS, 0, 0),
    ],
)
def test_a_killed_run_resumes_and_ends_identical(
    sequence, baseline, tmp_path, kill, committed_features, committed_matches, extracted_again, matched_again
):
    child = start_child(sequence, tmp_path, "killed", kill=kill)
    stdout, stderr = child.communicate(timeout=120)
    assert child.returncode == -9, stderr[-2000:]  # SIGKILL, not a clean exit
    assert "finished" not in stdout
    features, matches = stores(tmp_path)
    assert (len(features), len(matches)) == (committed_features, committed_matches)
    half_written = list(features.folder.glob(".shard-*.tmp"))
    assert len(half_written) == (1 if kill.startswith("flush") else 0)
    # No results that look complete; any half-written file is a hidden temporary one.
    folder = method_outputs.method_dir(tmp_path / "out", METHOD)
    assert not (folder / "pairs.csv").exists()
    assert scoring.methods_with_results(tmp_path / "out") == []
    visible = [p for p in folder.rglob("*") if p.is_file() and not p.name.startswith(".")] if folder.exists() else []
    assert all(p.suffix in (".h5", ".json") for p in visible), visible

    run_here(sequence, tmp_path)
    this_run = run_json(tmp_path / "out")["this_run"]
    assert extracted_again + matched_again < 40 + N_PAIRS  # finished work was kept, not redone
    assert this_run["extraction"] == {"images": 40, "cached": 40 - extracted_again, "extracted": extracted_again}
    assert this_run["matching"] == {"pairs": N_PAIRS, "cached": N_PAIRS - matched_again, "matched": matched_again}
    assert_same_pairs(tmp_path / "out", baseline["out"])
    assert not any(p.exists() for p in half_written)  # the dead writer's file was cleaned up
    features, matches = stores(tmp_path)
    reference_features, reference_matches = stores(baseline["out"].parent)
    assert_store_matches(features, reference_features)
    assert_store_matches(matches, reference_matches)


def test_a_damaged_shard_is_reported_by_name_not_read(tmp_path):
    store = ShardedStore(tmp_path / "s")
    with store.writer(flush_every=1) as writer:
        writer.put("a", {"x": np.arange(3)})
    damaged = tmp_path / "s" / f"shard-1-damaged{store_module.SHARD_SUFFIX}"
    damaged.write_bytes(b"\x89HDF\r\n\x1a\n" + b"\x00" * 40)
    with pytest.raises(StoreCorruptError, match=re.escape(f"shard {damaged} of the store")) as error:
        ShardedStore(tmp_path / "s").refresh()
    assert "Delete that file" in str(error.value)


# --------------------------------------------------------- 3. concurrent runs --
@pytest.mark.slow
@pytest.mark.real_data
def test_two_processes_writing_the_same_cache_and_output_at_once_corrupt_nothing(sequence, baseline, tmp_path):
    go = tmp_path / "go"
    children = [start_child(sequence, tmp_path, f"writer{i}", go_file=go) for i in range(2)]
    deadline = time.monotonic() + 120
    while not all((tmp_path / f"writer{i}.ready").exists() for i in range(2)):
        assert time.monotonic() < deadline and all(c.poll() is None for c in children), [
            c.communicate()[1][-2000:] for c in children if c.poll() is not None
        ]
        time.sleep(0.01)
    go.touch()
    for child in children:
        stdout, stderr = child.communicate(timeout=120)
        assert child.returncode == 0 and "finished" in stdout, stderr[-2000:]
    features, matches = stores(tmp_path)
    writers = {re.match(r"shard-(\d+)-", p.name).group(1) for p in features.shards()}
    assert len(writers) == 2, "both processes should have extracted at the same time"
    # Every copy of every entry, from either writer, equals the single-process run.
    reference_features, reference_matches = stores(baseline["out"].parent)
    assert_store_matches(features, reference_features)
    assert_store_matches(matches, reference_matches)
    assert_same_pairs(tmp_path / "out", baseline["out"])
    leftovers = [p.name for p in (tmp_path / "out").rglob(".*")] + [p.name for p in (tmp_path / "cache").rglob(".*")]
    assert leftovers == []  # no run left aside, no temporary file


# ------------------------------------------------------------- 4. determinism --
@pytest.mark.slow
@pytest.mark.real_data
def test_two_runs_from_scratch_give_identical_pairs_and_results(sequence, baseline, tmp_path):
    run_here(sequence, tmp_path)
    assert_same_pairs(tmp_path / "out", baseline["out"])
    first = (method_outputs.method_dir(baseline["out"], METHOD) / "pairs.csv").read_text().splitlines()
    second = (method_outputs.method_dir(tmp_path / "out", METHOD) / "pairs.csv").read_text().splitlines()
    # Byte-identical apart from the three trailing timing fields of each row.
    assert [line.rsplit(",", 3)[0] for line in first] == [line.rsplit(",", 3)[0] for line in second]
    results = [scoring.evaluate(out, write=False) for out in (baseline["out"], tmp_path / "out")]
    scores = ["sequence", "method", "n_pairs", "n_positives", "ap", "max_recall"]
    pd.testing.assert_frame_equal(results[0][scores], results[1][scores])
    assert 0 < results[0].loc[0, "ap"] <= 1


@pytest.mark.real_data
def test_the_params_seed_drives_every_random_choice_of_the_pair_builder(shared_data, tmp_path):
    def build(seed: int, name: str) -> bytes:
        params = config.load_params(
            config.PROJECT_ROOT / "params" / "gardens_point.yaml",
            seed=seed,
            pairs=str(tmp_path / name),
            output_dir=str(tmp_path / "out"),
        )
        sequence_build.prepare_sequence(params)
        return (tmp_path / name).read_bytes()

    assert build(0, "first.txt") == build(0, "second.txt")
    assert build(0, "first.txt") != build(1, "other_seed.txt")


@pytest.mark.slow
@pytest.mark.real_data
def test_two_jobs_store_what_one_job_stores(sequence, baseline, tmp_path):
    table = run_here(sequence, tmp_path, jobs=2)
    assert run_json(tmp_path / "out")["this_run"]["jobs"] == 2
    pd.testing.assert_frame_equal(table[SCORES], scoring.load_pairs_table(baseline["out"], METHOD)[SCORES])
    (features, matches), (reference_features, reference_matches) = stores(tmp_path), stores(baseline["out"].parent)
    assert len(features) == 40
    assert_store_matches(features, reference_features)
    assert_store_matches(matches, reference_matches)


@pytest.mark.real_data
def test_scores_do_not_depend_on_the_order_pairs_run_in(sequence, baseline, tmp_path):
    reversed_sequence = Sequence(sequence.name, sequence.image_root, sequence.pairs[::-1])
    shutil.copytree(baseline["cache"] / "features", tmp_path / "cache" / "features")  # every pair matched again
    table = run_here(reversed_sequence, tmp_path)
    assert run_json(tmp_path / "out")["this_run"]["matching"]["matched"] == len(sequence.pairs)
    expected = scoring.load_pairs_table(baseline["out"], METHOD)
    pd.testing.assert_frame_equal(table[SCORES].iloc[::-1].reset_index(drop=True), expected[SCORES])
