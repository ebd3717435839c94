"""A run holds the identity of everything its numbers depend on (images, weights, code), the caches are
keyed by it, and a run stands alone: its pages and exports need no cache. Small photographs, ORB."""

from __future__ import annotations

import json
import os
from pathlib import Path

import cv2
import pytest
from helpers import photo

from gvbench_nb.data.sequences import Pair, Sequence
from gvbench_nb.runner import image_features, method_outputs, method_runs

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


def run(root: Path, work: Path, pairs: list[Pair] = BMP_PAIRS):
    sequence = Sequence("photos", root, list(pairs))
    return method_runs.run_method(
        sequence, METHOD, PROFILE, work / "out", work / "cache", device="cpu", progress=False, threads=1
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
