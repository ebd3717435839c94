"""What a run holds in memory is bounded, whatever the number of pairs: open shards, cached
features, and the pipeline's peak allocations when the sequence grows."""

from __future__ import annotations

import tracemalloc
from pathlib import Path

import numpy as np
import pytest

from gvbench_nb.data.sequences import Pair, Sequence
from gvbench_nb.runner import image_features, method_runs, pair_matching
from gvbench_nb.runner.pair_matching import FeatureCache
from gvbench_nb.runner.store import ShardedStore


def test_reading_every_entry_keeps_a_bounded_number_of_shards_open(tmp_path):
    store = ShardedStore(tmp_path / "store", max_open=3)
    with store.writer(flush_every=2) as writer:  # 40 entries -> 20 shards
        for index in range(40):
            writer.put(f"key {index}", {"values": np.full(5, index)}, {"index": index})
    store.refresh()
    assert len(store.shards()) == 20
    for _ in range(2):  # a second pass reopens what was closed
        for index in range(40):
            entry = store.read(f"key {index}")
            assert entry["attr:index"] == index and (entry["values"] == index).all()
            assert len(store._open) <= 3
    store.close()


def test_feature_cache_holds_at_most_its_bytes_and_reads_each_hit_once():
    reads: list[str] = []

    def read(name: str) -> dict[str, np.ndarray]:
        reads.append(name)
        return {"descriptors": np.zeros((100, 10), np.float32)}  # 4,000 bytes

    cache = FeatureCache(read, max_bytes=10_000)
    for name in ["a", "b", "a", "c", "a", "d"]:
        assert cache.get(name)["descriptors"].shape == (100, 10)
        assert cache.nbytes <= 10_000
    assert reads == ["a", "b", "c", "d"]  # 'a' was used last before 'c': 'b' left first
    assert len(cache) == 2
    big = FeatureCache(lambda name: {"x": np.zeros(50_000, np.uint8)}, max_bytes=10_000)
    assert big.get("huge")["x"].size == 50_000 and len(big) == 1  # the newest always stays


def _fake_sequence(root: Path, references_per_query: int) -> Sequence:
    """20 queries against 40 references; every reference is used whatever the pair count."""
    step = 40 // references_per_query
    pairs = [
        Pair(f"q{q:02d}.jpg", f"r{(q + step * k) % 40:02d}.jpg", int(k == 0))
        for q in range(20)
        for k in range(references_per_query)
    ]
    return Sequence("fake", root, pairs)


def _peak_of_match_and_verify(tmp_path: Path, references_per_query: int) -> int:
    sequence = _fake_sequence(tmp_path / "images", references_per_query)
    verifier = {"type": "fundamental", "method": "FM_RANSAC", "threshold_px": 3.0, "confidence": 0.99, "max_iters": 20}
    verifier |= {"min_matches": 10**6, "min_match_score": 0.5}  # RANSAC skipped
    conf = {"method": "fake-nn", "profile": "test", "extractor": {"type": "colmap_sift", "name": "fake"}}
    conf |= {"matcher": {"type": "nn", "metric": "l2", "mutual": True, "ratio_threshold": 0.8}, "verifier": verifier}
    cache_dir = tmp_path / f"cache{references_per_query}"
    rng = np.random.default_rng(0)
    base = rng.normal(size=(200, 32))
    # Feature entries are keyed by image content: every image exists and differs.
    sequence.image_root.mkdir(parents=True, exist_ok=True)
    for index, name in enumerate(sequence.images):
        (sequence.image_root / name).write_bytes(f"image {index}".encode())
    with image_features.feature_store(cache_dir, conf["extractor"]).writer(flush_every=16) as writer:
        for name in sequence.images:  # noisy copies of one set: every pair has ~200 matches to hold or drop
            writer.put(
                image_features.image_key(sequence.image_root, name),
                {
                    "keypoints": rng.uniform(0, 500, (200, 2)).astype(np.float32),
                    "scores": np.ones(200, np.float32),
                    "descriptors": (base + 0.05 * rng.normal(size=base.shape)).astype(np.float32),
                    "image_size": np.array([500, 500]),
                },
                {"seconds": 0.01},
            )
    tracemalloc.start()
    pair_matching.match_and_verify(sequence, conf, cache_dir, device="cpu", progress=False, jobs=1)
    table = method_runs.pairs_table(sequence, conf, cache_dir, seed=0)
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    assert len(table) == len(sequence.pairs) and table["num_matches"].min() > 150
    return peak


@pytest.mark.slow
def test_pipeline_peak_memory_does_not_grow_with_the_pairs(tmp_path):
    """4x the pairs over the same 60 images (RANSAC skipped: it holds nothing): the peak may
    grow only by the pair table's rows (a few hundred bytes a pair), not by the ~3 KB of
    matches and scores a pair has."""
    _peak_of_match_and_verify(tmp_path, 4)  # first imports and one-time set-ups are not a pair's cost
    small = _peak_of_match_and_verify(tmp_path, 10)  # 200 pairs
    large = _peak_of_match_and_verify(tmp_path, 40)  # 800 pairs
    per_pair_growth = (large - small) / 600
    assert per_pair_growth < 1_500, f"peak grew by {per_pair_growth:.0f} bytes a pair ({small} -> {large})"
