"""A run holds the identity of everything its numbers depend on (images, weights, code), the caches are
keyed by it, and a run stands alone: its pages and exports need no cache. Small photographs, ORB."""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
from helpers import PAIRS, one_sentence, params_file, photo, run_cli

from gvbench_nb import methods
from gvbench_nb.data.sequences import Pair, Sequence
from gvbench_nb.protocol import weights
from gvbench_nb.runner import (
    config,
    distributed,
    image_features,
    input_checks,
    method_outputs,
    method_runs,
    score_files,
    scoring,
)
from gvbench_nb.studies import explore_pairs, failures, verifier_inputs

pytestmark = pytest.mark.reliability

METHOD, PROFILE = "orb-nn", "repository"
BMP_PAIRS = [
    Pair("query/a.bmp", "reference/a.bmp", 1),
    Pair("query/a.bmp", "reference/b.bmp", 0),
    Pair("query/b.bmp", "reference/b.bmp", 1),
    Pair("query/b.bmp", "reference/a.bmp", 0),
]


def bmp_root(root: Path) -> Path:
    """Uncompressed images: another photograph of the same size is a file of the same size."""
    for folder, warped in (("query", True), ("reference", False)):
        (root / folder).mkdir(parents=True, exist_ok=True)
        for letter, name in zip("ab", ("astronaut", "coffee")):
            cv2.imwrite(str(root / folder / f"{letter}.bmp"), photo(name, warped))
    return root


def run(root: Path, work: Path, pairs: list[Pair] = BMP_PAIRS, method: str = METHOD):
    sequence = Sequence("photos", root, list(pairs))
    return method_runs.run_method(
        sequence, method, PROFILE, work / "out", work / "cache", device="cpu", progress=False, threads=1
    )


def run_record(out: Path, method: str = METHOD) -> dict:
    return json.loads((method_outputs.method_dir(out, method) / "run.json").read_text())


def test_an_image_rewritten_in_place_with_its_size_mtime_and_inode_is_extracted_again(tmp_path, monkeypatch):
    root = bmp_root(tmp_path / "images")
    (tmp_path / "work" / "cache").mkdir(parents=True)  # as a run makes it before its work
    first = run(root, tmp_path / "work")
    assert (tmp_path / "work" / "cache" / image_features.CONTENT_KEYS_FILE).is_file()
    path = root / "query" / "a.bmp"
    before = path.stat()
    other = tmp_path / "other.bmp"
    cv2.imwrite(str(other), photo("chelsea", warped=True))
    assert other.stat().st_size == before.st_size
    with open(path, "r+b") as stream:  # in place: the same inode
        stream.write(other.read_bytes())
    os.utime(path, ns=(before.st_atime_ns, before.st_mtime_ns))
    after = path.stat()
    assert (after.st_size, after.st_mtime_ns, after.st_ino) == (before.st_size, before.st_mtime_ns, before.st_ino)
    monkeypatch.setattr(image_features, "_known_keys", {})  # a new process: only the saved memo is known
    second = run(root, tmp_path / "work")
    record = run_record(tmp_path / "work" / "out")["this_run"]
    assert record["extraction"] == {"images": 4, "cached": 3, "extracted": 1}
    assert record["matching"] == {"pairs": 4, "cached": 2, "matched": 2}
    fresh = run(root, tmp_path / "fresh")
    assert second["num_keypoints_query"].tolist() == fresh["num_keypoints_query"].tolist()
    assert second["num_keypoints_query"].tolist() != first["num_keypoints_query"].tolist()


# ------------------------------------------------------------------------ weights --
def test_other_bytes_at_a_published_checkpoint_are_named_before_any_work(tmp_path, root, empty_hub, capsys):
    empty_hub.mkdir(parents=True, exist_ok=True)
    (empty_hub / "xfeat.pt").write_bytes(b"other weights")
    found = weights.git_blob_id(empty_hub / "xfeat.pt")
    code, out, err = run_cli(capsys, "run", str(params_file(tmp_path, methods=["xfeat-nn"])))
    assert code != 0 and not (tmp_path / "out").exists()  # before any work
    sentence = one_sentence(err)
    published = weights.get("xfeat").git_blob
    assert published is not None
    for words in (str(empty_hub / "xfeat.pt"), found, published[0], "weights fetch xfeat", "--allow-other-weights"):
        assert words in sentence
    params = config.load_params(params_file(tmp_path, methods=["xfeat-nn"]))
    assert input_checks.check_run_inputs(params, allow_other_weights=True) == {}  # when the user says so


def register_weighted_orb(monkeypatch) -> str:
    """orb-nn's recipe, declaring that it loads the xfeat checkpoint (ORB reads nothing of it)."""
    for profile in list(methods.RECIPES):
        monkeypatch.setitem(methods.RECIPES, profile, dict(methods.RECIPES[profile]))
    monkeypatch.setattr(methods, "REGISTERED_FROM_CODE", set())
    recipe = methods.resolve_method(METHOD, PROFILE)
    extractor = {**recipe["extractor"], "checkpoints": ["xfeat"]}
    methods.register_method("orb-weighted", {PROFILE: {"extractor": extractor, "matcher": recipe["matcher"]}})
    return "orb-weighted"


def test_a_run_records_its_weights_and_other_weights_never_reuse_cached_features(tmp_path, monkeypatch, empty_hub):
    import torch

    method = register_weighted_orb(monkeypatch)
    root = bmp_root(tmp_path / "images")
    empty_hub.mkdir(parents=True, exist_ok=True)
    checkpoint = empty_hub / "xfeat.pt"
    torch.save({"weight": torch.zeros(3)}, checkpoint)
    run(root, tmp_path / "work", method=method)
    record = run_record(tmp_path / "work" / "out", method)
    first = weights.git_blob_id(checkpoint)
    assert record["weights"] == {"xfeat.pt": {"path": str(checkpoint), "blob": first, "published": False}}
    assert record["this_run"]["extraction"]["extracted"] == 4
    torch.save({"weight": torch.ones(3)}, checkpoint)  # other weights at the checkpoint's path
    run(root, tmp_path / "work", method=method)
    record = run_record(tmp_path / "work" / "out", method)
    assert record["weights"]["xfeat.pt"]["blob"] not in (first, None)
    assert record["this_run"]["extraction"] == {"images": 4, "cached": 0, "extracted": 4}
    assert record["this_run"]["matching"]["cached"] == 0


def test_a_run_records_the_code_it_ran_with(tmp_path):
    run(bmp_root(tmp_path / "images"), tmp_path / "work")
    record = run_record(tmp_path / "work" / "out")
    assert record["code_digest"] == method_runs.code_digest() and record["weights"] == {}
    assert distributed.package_code().endswith(f"(code {record['code_digest']})")


# --------------------------------------------------------------- a run stands alone --
def test_pages_and_exports_of_a_run_work_with_its_cache_deleted(tmp_path, root, capsys):
    run(root, tmp_path / "work", pairs=PAIRS)
    out, cache = tmp_path / "work" / "out", tmp_path / "work" / "cache"
    table = scoring.load_pairs_table(out, METHOD)
    pair = table.iloc[0]
    before = verifier_inputs.match_lines(out, METHOD, pair["query"], pair["reference"])
    shutil.rmtree(cache)
    capsys.readouterr()
    after = verifier_inputs.match_lines(out, METHOD, pair["query"], pair["reference"])
    said = capsys.readouterr().out
    assert said.count("\n") == 1 and "lacks 1 pair(s) of this run" in said and str(cache) in said
    for name in before:  # the page draws what the run computed
        np.testing.assert_array_equal(before[name], after[name])
    shutil.rmtree(cache)
    rows = failures.failures_table({METHOD: table}, k=2, image_root=root)
    failures.failure_pairs(rows, out, METHOD, root)
    said = capsys.readouterr().out  # one line for the page
    assert said.count("\n") == 1 and f"lacks {len(rows)} pair(s) of this run" in said
    shutil.rmtree(cache)
    views = explore_pairs.pair_views(out, {METHOD: table}, 2, tmp_path / "figures")
    assert views["table"]["pair_index"].tolist() == [2]
    shutil.rmtree(cache)
    path, _ = score_files.export_npy(out, METHOD)
    assert path.is_file()
