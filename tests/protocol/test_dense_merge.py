"""LoFTR as hloc runs it: the image swap and the merging of dense matches into keypoints
(hloc's match_dense.py, conf `loftr`), against a reference written from that rule."""

from __future__ import annotations

import cv2
import numpy as np
import pandas as pd
import pytest
import torch

from gvbench_nb import methods
from gvbench_nb.data.sequences import Pair, Sequence
from gvbench_nb.protocol import matching as matchers
from gvbench_nb.protocol import registry
from gvbench_nb.protocol.matching.base import Matcher
from gvbench_nb.protocol.matching.loftr import LoFTRMatcher, loftr_call, merge_dense_matches
from gvbench_nb.runner import method_runs, pair_matching


def hloc_merge_reference(pairs, raw, max_keypoints):
    """hloc's rule for 1-px cells and error, distinct scores: pairs by fewer image uses then names;
    cell round(x + 0.5) - 0.5; cell scores summed; max_keypoints best cells kept; matches to the
    nearest kept cell within 1 px, best-scored per keypoint on both sides; float16 scores."""
    uses = {}
    for pair in pairs:
        for name in pair:
            uses[name] = uses.get(name, 0) + 1
    order = sorted(range(len(pairs)), key=lambda i: (min(uses[pairs[i][0]], uses[pairs[i][1]]), pairs[i]))
    cells: dict[str, dict] = {}
    for i in order:
        for side, name in enumerate(pairs[i]):
            for point, score in zip(raw[i][side], raw[i][2]):
                cell = tuple(float(np.round(np.float32(v) + np.float32(0.5)) - 0.5) for v in point)
                table = cells.setdefault(name, {})
                table[cell] = np.float32(table.get(cell, np.float32(0)) + np.float32(score))
    keypoints = {}
    for name, table in cells.items():
        best = sorted(table.items(), key=lambda item: -item[1])[:max_keypoints]
        keypoints[name] = np.array([cell for cell, _ in best], np.float32).reshape(-1, 2)
    merged = []
    for (name0, name1), (points0, points1, scores) in zip(pairs, raw):
        candidates = []
        for p0, p1, score in zip(points0, points1, scores):
            ids = []
            for point, name in ((p0, name0), (p1, name1)):
                distance = np.linalg.norm(keypoints[name] - point, axis=1)
                ids.append(int(np.argmin(distance)) if len(distance) and distance.min() <= 1 else -1)
            if min(ids) >= 0:
                candidates.append((ids[0], ids[1], float(score)))
        kept = [
            c
            for c in candidates
            if c[2] == max(o[2] for o in candidates if o[0] == c[0])
            and c[2] == max(o[2] for o in candidates if o[1] == c[1])
        ]
        kept.sort(key=lambda c: c[0])
        merged.append(
            (
                np.array([c[:2] for c in kept], np.int64).reshape(-1, 2),
                np.array([c[2] for c in kept], np.float32).astype(np.float16).astype(np.float32),
            )
        )
    return keypoints, merged


def _raw(points0, points1, scores):
    return (
        np.array(points0, np.float32).reshape(-1, 2),
        np.array(points1, np.float32).reshape(-1, 2),
        np.array(scores, np.float32),
    )


def test_points_of_one_cell_across_pairs_become_one_keypoint():
    pairs = [("q", "a"), ("q", "b")]
    raw = [_raw([[10.2, 20.1]], [[5.3, 5.3]], [0.9]), _raw([[10.4, 20.3]], [[7.7, 7.7]], [0.8])]
    keypoints, merged = merge_dense_matches(pairs, raw)
    np.testing.assert_array_equal(keypoints["q"], [[10.5, 20.5]])
    np.testing.assert_array_equal(keypoints["a"], [[5.5, 5.5]])
    np.testing.assert_array_equal(keypoints["b"], [[7.5, 7.5]])
    assert [m.tolist() for m, _ in merged] == [[[0, 0]], [[0, 0]]]
    with pytest.raises(ValueError, match="2 pairs but 1 raw match sets"):
        merge_dense_matches(pairs, raw[:1])


def test_the_cap_keeps_the_best_cells_and_reassigns_to_a_neighbouring_kept_cell():
    # Image q gets four cells: 0.5,0.5 (0.8, from pair q-b), 5.5,0.5 (0.35), 1.5,0.5 (0.3)
    # and 9.5,9.5 (0.25). A cap of 2 keeps the first two. The match at q (1.1, 0.4) lost its
    # cell but lies 0.61 px from the kept 0.5,0.5 keypoint: it moves there. The match at
    # q (9.2, 9.2) has no kept keypoint within 1 px: it is dropped. Pair a-c gives a's cell
    # 20.5 the mass to survive a's own cap.
    pairs = [("q", "a"), ("q", "b"), ("a", "c")]
    raw = [
        _raw([[1.1, 0.4], [5.2, 0.2], [9.2, 9.2]], [[20.2, 20.2], [30.2, 30.2], [70.2, 70.2]], [0.3, 0.35, 0.25]),
        _raw([[0.3, 0.3]], [[50.2, 50.2]], [0.8]),
        _raw([[20.3, 20.3]], [[60.2, 60.2]], [0.95]),
    ]
    keypoints, merged = merge_dense_matches(pairs, raw, max_keypoints=2)
    np.testing.assert_array_equal(keypoints["q"], [[0.5, 0.5], [5.5, 0.5]])
    np.testing.assert_array_equal(keypoints["a"], [[20.5, 20.5], [30.5, 30.5]])
    np.testing.assert_array_equal(merged[0][0], [[0, 0], [1, 1]])
    np.testing.assert_array_equal(merged[0][1], np.float16([0.3, 0.35]).astype(np.float32))
    # Without the cap every cell stays and the three matches keep their own cells.
    keypoints, merged = merge_dense_matches(pairs, raw, max_keypoints=None)
    assert len(keypoints["q"]) == 4 and len(merged[0][0]) == 3


def test_many_to_one_matches_keep_the_best_scored_on_each_side():
    pairs = [("q", "a")]
    # Two points of a in one cell matched from different cells of q: only 0.8 stays.
    raw = [_raw([[3.2, 3.2], [9.2, 9.2]], [[4.2, 4.2], [4.4, 4.1]], [0.6, 0.8])]
    keypoints, merged = merge_dense_matches(pairs, raw)
    assert len(keypoints["a"]) == 1
    np.testing.assert_array_equal(keypoints["q"][merged[0][0][:, 0]], [[9.5, 9.5]])
    np.testing.assert_allclose(merged[0][1], np.float16([0.8]).astype(np.float32))


@pytest.mark.parametrize("seed", range(3))
def test_merging_equals_hloc_rule_on_random_dense_matches(seed):
    rng = np.random.default_rng(seed)
    names = [f"image{i}" for i in range(5)]
    pairs = [(names[i], names[j]) for i in range(5) for j in range(5) if i < j and rng.random() < 0.8]
    # Points near a few dozen places an image, so cells collide across pairs, cells next to a
    # dropped cell exist, and several matches share a cell.
    places = {name: rng.uniform(0, 40, (35, 2)) for name in names}
    raw = []
    for name0, name1 in pairs:
        n = int(rng.integers(20, 60))
        points0 = places[name0][rng.integers(0, 35, n)] + rng.normal(0, 0.7, (n, 2))
        points1 = places[name1][rng.integers(0, 35, n)] + rng.normal(0, 0.7, (n, 2))
        raw.append(_raw(points0, points1, rng.uniform(0.2, 1.0, n)))
    keypoints, merged = merge_dense_matches(pairs, raw, max_keypoints=40)
    expected_keypoints, expected = hloc_merge_reference(pairs, raw, max_keypoints=40)
    assert any(len(v) == 40 for v in keypoints.values())  # the cap bites
    for name in expected_keypoints:
        np.testing.assert_array_equal(keypoints[name], expected_keypoints[name])
    kept = dropped = 0
    for (matches, scores), (expected_matches, expected_scores), pair_raw in zip(merged, expected, raw):
        np.testing.assert_array_equal(matches, expected_matches)
        np.testing.assert_array_equal(scores, expected_scores)
        kept, dropped = kept + len(matches), dropped + len(pair_raw[2]) - len(matches)
    assert kept > 50 and dropped > 50  # the rule keeps and removes matches here


def test_loftr_runs_on_the_swapped_pair_and_returns_points_in_our_order():
    seen = {}

    def model(data):
        seen.update(data)
        # A fake LoFTR: its first image's points at x = that image's mean, second's at 2x.
        return {
            "keypoints0": data["image0"].mean().reshape(1, 1).repeat(1, 2),
            "keypoints1": 2 * data["image1"].mean().reshape(1, 1).repeat(1, 2),
            "confidence": torch.tensor([0.7]),
        }

    image0, image1 = torch.full((1, 1, 8, 8), 1.0), torch.full((1, 1, 8, 8), 3.0)
    points0, points1, confidence = loftr_call(model, image0, image1)
    assert seen["image0"] is image1 and seen["image1"] is image0
    np.testing.assert_array_equal(points0, [[2.0, 2.0]])  # our image 0 was the network's second
    np.testing.assert_array_equal(points1, [[3.0, 3.0]])
    np.testing.assert_array_equal(confidence, np.float32([0.7]))
    # The fork's matching/im_models/loftr.py hands LoFTR image0 and image1 in the pair's order;
    # hloc's matchers/loftr.py swaps them. The recipes say which each profile does.
    points0, points1, _ = loftr_call(model, image0, image1, swap_images=False)
    assert seen["image0"] is image0 and seen["image1"] is image1
    np.testing.assert_array_equal(points0, [[1.0, 1.0]])
    np.testing.assert_array_equal(points1, [[6.0, 6.0]])
    assert methods.resolve_method("loftr", "repository")["matcher"]["swap_images"] is False
    assert methods.resolve_method("loftr", "paper")["matcher"]["swap_images"] is True


class _FakeDense:
    """Stands in for LoFTR: the same textured points in both images, shifted by the pair."""

    dense = True

    def __call__(self, image0: np.ndarray, image1: np.ndarray):
        rng = np.random.default_rng(int(image0.sum() + image1.sum()) % 1000)
        points = rng.uniform(5, 55, (80, 2)).astype(np.float32)
        return points, points + np.float32(0.3), rng.uniform(0.55, 1.0, 80).astype(np.float32)


@pytest.mark.reliability
def test_the_dense_pipeline_merges_across_all_pairs_and_resumes(tmp_path, monkeypatch):
    root = tmp_path / "images"
    root.mkdir()
    rng = np.random.default_rng(0)
    for name in ("q.png", "a.png", "b.png"):
        cv2.imwrite(str(root / name), rng.integers(0, 256, (64, 64), dtype=np.uint8))
    pairs = [Pair("q.png", "a.png", 1), Pair("q.png", "b.png", 0)]
    sequence = Sequence(name="dense", image_root=root, pairs=pairs)
    conf = methods.resolve_method("loftr", "paper")
    monkeypatch.setattr(matchers, "build_matcher", lambda matcher_conf, device: _FakeDense())
    cache = tmp_path / "cache"
    pair_matching.match_and_verify(sequence, conf, cache, "cpu", progress=False)
    table = method_runs.pairs_table(sequence, conf, cache, seed=0)

    raw = pair_matching.raw_dense_store(cache, conf)
    entries = [raw.read(pair_matching.pair_key(root, p.query, p.reference, 0)) for p in pairs]
    keypoints, merged = merge_dense_matches(
        [(p.query, p.reference) for p in pairs], [(e["points0"], e["points1"], e["scores"]) for e in entries]
    )
    assert table["num_matches"].tolist() == [len(m) for m, _ in merged]
    keys = pair_matching.pair_keys(sequence, 0)
    stored = pair_matching.match_store(cache, conf, keys).read(pair_matching.pair_key(root, "q.png", "b.png", 0))
    np.testing.assert_array_equal(stored["points0"], keypoints["q.png"][merged[1][0][:, 0]])

    # Merged results hold for their pair list only: another list (any output folder's) is merged over
    # itself, from the raw matches kept, in a store of its own; the first list's results stay.
    shorter = Sequence(name="dense", image_root=root, pairs=pairs[:1])
    counts = pair_matching.match_and_verify(shorter, conf, cache, "cpu", progress=False)
    assert counts["cached"] == 0 and counts["matched"] == 1
    alone = method_runs.pairs_table(shorter, conf, cache, seed=0)
    _, merged_alone = merge_dense_matches(
        [("q.png", "a.png")], [(e["points0"], e["points1"], e["scores"]) for e in entries[:1]]
    )
    assert alone["num_matches"].tolist() == [len(merged_alone[0][0])]
    pd.testing.assert_frame_equal(method_runs.pairs_table(sequence, conf, cache, seed=0), table)


def test_loftr_conf_merges_as_hloc_conf_loftr():
    options = pair_matching.dense_merge_options(methods.resolve_method("loftr", "paper")["matcher"])
    assert options == {"max_keypoints": 8192, "cell_size": 1, "max_error": 1}
    assert registry.model_class("matcher type", Matcher, matchers.__name__, {"type": "kornia_loftr"}) is LoFTRMatcher
