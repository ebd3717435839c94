"""Each image's bytes are hashed once: once in a process, and once for every process sharing a cache folder
(its content-keys file), again only when the file changed."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import cv2
import pytest
from helpers import PAIRS

from gvbench_nb.data.sequences import Sequence
from gvbench_nb.runner import image_features, input_checks, method_runs, pair_matching, scoring

# A process of its own: checks the images as a run does first, counting the files whose bytes it hashes
# (every BLAKE2b image_features makes), and prints their content keys.
SECOND_PROCESS = """
import json, sys
from pathlib import Path
from gvbench_nb.data.sequences import Pair, Sequence
from gvbench_nb.runner import image_features, input_checks

hashed = []
real = image_features.hashlib


class Counting:
    def blake2b(self, *args, **kwargs):
        hashed.append(1)
        return real.blake2b(*args, **kwargs)


image_features.hashlib = Counting()
root, cache, pairs = sys.argv[1], sys.argv[2], json.loads(sys.argv[3])
sequence = Sequence("photos", Path(root), [Pair(*pair) for pair in pairs])
input_checks.check_image_contents(sequence, cache, allow_damaged=False)  # what a run checks first
keys = {name: image_features.image_key(sequence.image_root, name) for name in sequence.images}
print(json.dumps({"keys": keys, "hashed": len(hashed)}))
"""


class _CountingHashlib:
    """``image_features``'s hashlib, counting BLAKE2b digests (each one a file's bytes read whole)."""

    def __init__(self) -> None:
        import hashlib

        self.real, self.count = hashlib, 0

    def __getattr__(self, name: str):
        return getattr(self.real, name)

    def blake2b(self, *args, **kwargs):
        self.count += 1
        return self.real.blake2b(*args, **kwargs)


def _second_process(root: Path, cache: Path, pairs: list) -> dict:
    done = subprocess.run(
        [
            sys.executable,
            "-c",
            SECOND_PROCESS,
            str(root),
            str(cache),
            json.dumps([[p.query, p.reference, p.label] for p in pairs]),
        ],
        capture_output=True,
        text=True,
        check=True,
        env={**os.environ, "PYTHONPATH": str(Path(image_features.__file__).parents[2])},
    )
    return json.loads(done.stdout.splitlines()[-1])


@pytest.mark.reliability
def test_a_run_hashes_each_image_once_in_its_process(root, tmp_path, monkeypatch):
    from gvbench_nb.runner import run_estimate

    counting = _CountingHashlib()
    monkeypatch.setattr(image_features, "hashlib", counting)
    monkeypatch.setattr(image_features, "_known_keys", {}, raising=False)
    sequence = Sequence("photos", root, list(PAIRS))
    cache, out = tmp_path / "cache", tmp_path / "out"
    # What a run asks of the images, each step on its own: the checks, the estimate, the run, its binding.
    input_checks.check_image_contents(sequence, cache, allow_damaged=False)
    run_estimate.long_run_note(
        {
            "methods": ["sift-nn"],
            "profile": "paper",
            "cache_dir": str(cache),
            "output_dir": str(out),
            "seed": 0,
            "verifier": None,
        },
        sequence,
    )
    for _ in range(2):
        method_runs.run_method(sequence, "sift-nn", "paper", out, cache, device="cpu", progress=False, threads=1)
    pair_matching.pair_keys(sequence, 0)
    scoring.sequence_binding(sequence)
    assert counting.count == len(sequence.images)


@pytest.mark.reliability
def test_a_second_process_reuses_the_saved_keys_and_hashes_a_changed_image_again(root, tmp_path):
    sequence = Sequence("photos", root, list(PAIRS))
    changed = sequence.images[1]
    image = cv2.imread(str(root / changed))
    cv2.imwrite(str(root / changed), image, [cv2.IMWRITE_PNG_COMPRESSION, 0])  # a pixel changed keeps its size
    cache = tmp_path / "cache"
    cache.mkdir()
    input_checks.check_image_contents(sequence, cache, allow_damaged=False)
    keys = {name: image_features.image_key(root, name) for name in sequence.images}
    second = _second_process(root, cache, PAIRS)
    assert second == {"keys": keys, "hashed": 0}

    # One image replaced by other bytes of the same size, a second later: hashed again, the others not.
    before = (root / changed).stat()
    image[0, 0] ^= 0xFF
    cv2.imwrite(str(root / changed), image, [cv2.IMWRITE_PNG_COMPRESSION, 0])
    os.utime(root / changed, ns=(before.st_atime_ns, before.st_mtime_ns + 1_000_000_000))
    assert (root / changed).stat().st_size == before.st_size
    third = _second_process(root, cache, PAIRS)
    assert third["hashed"] == 1
    assert third["keys"] == {**keys, changed: third["keys"][changed]}
    assert third["keys"][changed] != keys[changed]
    # This process sees the change too, and so do the pairs' keys made of it.
    assert {name: image_features.image_key(root, name) for name in sequence.images} == third["keys"]
    assert pair_matching.pair_keys(sequence, 0) == {
        pair: pair_matching.pair_key(root, pair.query, pair.reference, 0) for pair in sequence.pairs
    }
    assert any(third["keys"][changed] in key for key in pair_matching.pair_keys(sequence, 0).values())


@pytest.mark.reliability
def test_processes_saving_keys_at_once_lose_none(root, tmp_path):
    cache = tmp_path / "cache"
    cache.mkdir()
    pairs = list(PAIRS)
    commands = [
        [
            sys.executable,
            "-c",
            SECOND_PROCESS,
            str(root),
            str(cache),
            json.dumps([[pair.query, pair.reference, pair.label]]),
        ]
        for pair in pairs
    ]
    env = {**os.environ, "PYTHONPATH": str(Path(image_features.__file__).parents[2])}
    running = [subprocess.Popen(c, stdout=subprocess.PIPE, env=env) for c in commands]
    assert all(process.wait() == 0 for process in running)
    assert _second_process(root, cache, pairs)["hashed"] == 0
