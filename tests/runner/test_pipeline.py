"""The pipeline on real pairs: cache reuse, resumable stores, the results contract."""

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from helpers import check_stage_outputs

from gvbench_nb import methods
from gvbench_nb.data.sequences import Pair, Sequence, read_pairs
from gvbench_nb.runner import (
    concurrency,
    config,
    image_features,
    method_outputs,
    method_runs,
    runs,
    scoring,
    sequence_build,
)
from gvbench_nb.runner.store import ShardedStore

PAIRS_COLUMNS = {"query", "reference", "label", "num_matches", "num_inliers", "score", "extract_seconds"}
PAIRS_COLUMNS |= {"match_seconds", "verify_seconds"}
RESULTS_COLUMNS = {"method", "n_pairs", "n_positives", "ap", "max_recall", "seconds_per_pair"}


def gardens_point(shared_data: Path, queries=(40, 120), far=60) -> Sequence:
    """Two queries, each with two true references and one far-apart false one."""
    pairs = [
        Pair(f"night_right/Image{q:03d}.jpg", f"day_right/Image{r:03d}.jpg", label)
        for q in queries
        for r, label in ((q, 1), (q + 1, 1), ((q + far) % 200, 0))
    ]
    return Sequence("gp_test", shared_data / "gardens_point", pairs)


@pytest.mark.real_data
def test_second_run_extracts_and_matches_nothing(shared_data, tmp_path):
    sequence = gardens_point(shared_data)
    first = method_runs.run_method(sequence, "sift-nn", "paper", tmp_path / "out", tmp_path / "cache", progress=False)
    run = pd.read_json(method_outputs.method_dir(tmp_path / "out", "sift-nn") / "run.json", typ="series")
    assert run["this_run"]["extraction"] == {"images": 8, "cached": 0, "extracted": 8}
    # Extraction time is amortised over the pairs of each image.
    store = image_features.feature_store(tmp_path / "cache", methods.resolve_method("sift-nn")["extractor"])
    total = sum(float(store.read(k)["attr:seconds"]) for k in store.keys())
    assert first["extract_seconds"].sum() == pytest.approx(total, rel=1e-6)
    # A second run into the folder adds a run of its own, made from the caches.
    second = method_runs.run_method(sequence, "sift-nn", "paper", tmp_path / "out", tmp_path / "cache", progress=False)
    run = pd.read_json(method_outputs.method_dir(tmp_path / "out", "sift-nn") / "run.json", typ="series")
    assert run["this_run"]["extraction"] == {"images": 8, "cached": 8, "extracted": 0}
    assert run["this_run"]["matching"] == {"pairs": 6, "cached": 6, "matched": 0}
    pd.testing.assert_frame_equal(first, second)
    assert set(first.columns) >= PAIRS_COLUMNS
    # Another method with the same extractor conf reuses the cached features.
    method_runs.run_method(sequence, "orb-nn", "paper", tmp_path / "out", tmp_path / "cache", progress=False)
    assert len(list((tmp_path / "cache" / "features").iterdir())) == 2  # sift + orb, once each


def test_store_resumes_and_ignores_half_written_shards(tmp_path):
    store = ShardedStore(tmp_path / "s")
    with store.writer(flush_every=2) as writer:
        for i in range(3):
            writer.put(f"img/{i}.png", {"x": np.full(3, i)}, {"seconds": 0.5})
    # A writer killed mid-shard leaves only a hidden temporary file: readers skip it.
    (tmp_path / "s" / ".shard-999-dead.tmp").write_bytes(b"\x89HDF half written")
    reread = ShardedStore(tmp_path / "s")
    assert sorted(reread.keys()) == ["img/0.png", "img/1.png", "img/2.png"]
    assert reread.read("img/2.png")["x"].tolist() == [2, 2, 2]
    assert reread.read("img/1.png")["attr:seconds"] == 0.5
    assert len(reread.shards()) == 2
    # A reader that needs only some arrays (or only the attributes) gets only those.
    with store.writer() as writer:
        writer.put("both", {"keypoints": np.zeros((4, 2)), "descriptors": np.ones((4, 8))}, {"seconds": 1.0})
    reread.refresh()
    assert set(reread.read("both", fields=("keypoints", "absent"))) == {"keypoints", "attr:seconds"}
    assert set(reread.read("both", fields=())) == {"attr:seconds"}
    assert set(reread.read("both")) == {"keypoints", "descriptors", "attr:seconds"}


def test_prefetch_preserves_order_and_surfaces_errors_in_place():
    def load(i):
        time.sleep(0.01 * (5 - i % 5))  # later items finish first
        if i == 3:
            raise OSError("bad image 3")
        return i * 10

    results = list(concurrency.prefetch(range(8), load, depth=4, jobs=3))
    assert [item for item, _ in results] == list(range(8))
    assert [r for i, r in results if i != 3] == [0, 10, 20, 40, 50, 60, 70]
    assert isinstance(results[3][1], OSError)


@pytest.mark.slow
@pytest.mark.real_data
def test_cli_run_writes_the_results_contract(shared_data, tmp_path):
    output, params = tmp_path / "gp", config.PROJECT_ROOT / "params" / "gardens_point.yaml"
    argv = ["run", str(params), "--methods", "sift-nn", "--limit", "24", "--output-dir", str(output)]
    completed = subprocess.run([sys.executable, "-m", "gvbench_nb", *argv], capture_output=True, text=True, timeout=600)
    assert completed.returncode == 0, completed.stderr[-3000:]
    assert f"results table: {output / 'results.csv'}" in completed.stdout
    results = pd.read_csv(output / "results.csv")
    assert set(results.columns) >= RESULTS_COLUMNS
    pairs = pd.read_csv(method_outputs.method_dir(output, "sift-nn") / "pairs.csv")
    assert set(pairs.columns) >= PAIRS_COLUMNS
    sequence = sequence_build.prepare_sequence(config.load_params(params, limit=24))
    assert len(sequence.pairs) == 24
    check_stage_outputs(output, "sift-nn", sequence.pairs)  # one row a pair, metrics recomputed from them
    notebooks = ["01_sequence.ipynb", "02_verify_sift-nn.ipynb", "03_evaluate.ipynb"]
    figures = ["pr_curves.png", "sequence_examples.png", "inliers_sift-nn.png"]
    (run, manifest), *earlier = runs.finished_runs(output)
    assert earlier == [] and manifest["door"] == "run" and manifest["methods"] == ["sift-nn"]
    assert [name for name in notebooks + figures if not (run / name).is_file()] == []


def tiny_sequence(root: Path) -> Sequence:
    from gvbench_nb.data import synthetic

    synthetic.generate_sample(root, n_frames=6, image_size=(160, 120))
    return Sequence("tiny", root, read_pairs(root / "pairs.txt")[:6])


def test_run_method_finds_its_finished_result_done_without_torch_and_redoes_another(tmp_path):
    """What ``run`` does: the method computed in one process into the run being built, then its
    notebook's run_method (given that run as its output folder) finds it done."""
    sequence = tiny_sequence(tmp_path / "data")
    out, cache = runs.start(tmp_path / "out", "run"), tmp_path / "cache"
    first = method_runs.run_method(sequence, "sift-nn", "repository", out, cache, device="cpu", progress=False)
    written = {name: (out / "sift-nn" / name).read_bytes() for name in ("pairs.csv", "run.json")}
    code = (
        "import sys, json; from pathlib import Path\n"
        "from gvbench_nb.runner import method_runs\nfrom gvbench_nb.data.sequences import Sequence, read_pairs\n"
        f"root = Path({str(tmp_path / 'data')!r})\n"
        "sequence = Sequence('tiny', root, read_pairs(root / 'pairs.txt')[:6])\n"
        f"table = method_runs.run_method(sequence, 'sift-nn', 'repository', Path({str(out)!r}), Path({str(cache)!r}), "
        "device='cpu', progress=False)\n"
        "print(len(table), json.dumps([m for m in ('torch', 'kornia') if m in sys.modules]))"
    )
    env = {**os.environ, "PYTHONPATH": str(config.PROJECT_ROOT)}
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300, env=env)
    assert done.returncode == 0, done.stderr[-2000:]
    assert done.stdout.strip().splitlines()[-1] == "6 []"
    assert {name: (out / "sift-nn" / name).read_bytes() for name in written} == written  # found, not rewritten

    # Another device request (or seed, conf, pairs, labels, images) is another result: made again, from the caches.
    again = method_runs.run_method(sequence, "sift-nn", "repository", out, cache, device="auto", progress=False)
    run = json.loads((out / "sift-nn" / "run.json").read_text())
    assert run["device_request"] == "auto" and run["this_run"]["matching"] == {"pairs": 6, "cached": 6, "matched": 0}
    pd.testing.assert_frame_equal(first, again)
    shorter = method_runs.run_method(sequence.limited(4), "sift-nn", "repository", out, cache, progress=False)
    assert len(shorter) == 4 and len(scoring.load_pairs_table(out, "sift-nn")) == 4
