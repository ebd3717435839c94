"""LightGlue split into a per-image and a per-pair part gives kornia's matches and scores
bit for bit; the per-image cache is bounded and thread-safe; the cross-attention through
torch's fused kernel (matcher conf ``cross_attention: sdpa``) agrees with kornia's."""

import threading
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from gvbench_nb import methods
from gvbench_nb.protocol import features as extractors
from gvbench_nb.protocol import images
from gvbench_nb.protocol import matching as matchers
from gvbench_nb.protocol.matching import lightglue_prepared
from gvbench_nb.runner.pair_matching import PreparedCache

# Two true pairs (many matches: LightGlue runs deep and prunes) and false pairs (it stops early).
IMAGES = [
    "night_right/Image060.jpg",
    "day_right/Image060.jpg",
    "day_right/Image061.jpg",
    "day_right/Image140.jpg",
    "night_right/Image140.jpg",
]


# The best 1024 of an image's keypoints (the profile keeps 2048): equality holds for any number,
# and attention over half the keypoints costs about a quarter; true pairs keep hundreds of matches.
MAX_KEYPOINTS = 1024


def features_of(shared_data: Path, method: str, names: list[str] = IMAGES) -> tuple[dict, list[dict]]:
    conf = methods.resolve_method(method, "repository")
    if conf["extractor"].get("model_input_long_side"):  # a quarter of the pixels: the split is what is compared
        conf["extractor"]["model_input_long_side"] = 512
    extractor = extractors.build_extractor(conf["extractor"], torch.device("cpu"))
    features = []
    for name in names:
        image, _ = images.load_for_extraction(shared_data / "gardens_point" / name, conf["extractor"])
        found = extractor(image)
        best = np.argsort(-found["scores"], kind="stable")[:MAX_KEYPOINTS]
        found = {key: value[best] for key, value in found.items()}
        found["image_size"] = np.array(image.shape[:2][::-1], np.float32)
        features.append(found)
    return conf, features


@pytest.fixture(scope="module")
def disk_features(shared_data):
    return features_of(shared_data, "disk-lg")


@pytest.mark.slow
@pytest.mark.real_data
@pytest.mark.parametrize(
    "method, options",
    [
        ("disk-lg", {}),
        ("disk-lg", {"depth_confidence": -1, "width_confidence": -1}),
        ("aliked-lg", {}),  # other weights, widths and depths
        ("xfeat-lg", {}),
    ],
    ids=["paper-early-stop-and-pruning", "all-layers-no-pruning", "aliked-lg", "xfeat-lg"],
)
def test_prepared_matches_equal_kornia_bit_for_bit(disk_features, shared_data, method, options):
    conf, features = disk_features if method == "disk-lg" else features_of(shared_data, method)
    matcher = matchers.build_matcher({**conf["matcher"], **options}, torch.device("cpu"))
    assert matcher.can_prepare
    prepared = [matcher.prepare(f) for f in features]
    counts = []
    for i, j in [(0, 1), (0, 2), (1, 0), (0, 3), (4, 3), (4, 1)] if method == "disk-lg" else [(0, 1), (0, 3)]:
        expected_matches, expected_scores = matcher(features[i], features[j])
        got_matches, got_scores = matcher.match_prepared(prepared[i], prepared[j])
        assert got_matches.dtype == np.int64 and got_scores.dtype == np.float32
        np.testing.assert_array_equal(got_matches, expected_matches, err_msg=f"{method} {IMAGES[i]} {IMAGES[j]}")
        np.testing.assert_array_equal(got_scores, expected_scores, err_msg=f"{method} {IMAGES[i]} {IMAGES[j]}")
        counts.append(len(expected_matches))
    if method == "disk-lg":  # true and false pairs, not all alike
        assert max(counts) > 100 and min(counts) < max(counts) / 2


@pytest.mark.slow
@pytest.mark.real_data
def test_prepared_image_without_keypoints_matches_nothing_and_mixed_precision_refuses(disk_features):
    conf, features = disk_features
    matcher = matchers.build_matcher(conf["matcher"], torch.device("cpu"))
    empty = {**features[0], "keypoints": features[0]["keypoints"][:0], "descriptors": features[0]["descriptors"][:0]}
    assert matcher.prepare(empty) is None
    pair_matches, scores = matcher.match_prepared(None, matcher.prepare(features[1]))
    assert pair_matches.shape == (0, 2) and scores.shape == (0,)
    matcher.model.conf.mp = True
    assert not lightglue_prepared.supports_prepared(matcher.model)


class Sized:
    def __init__(self, size: int):
        self.size = size

    def nbytes(self) -> int:
        return self.size


def test_prepared_cache_drops_least_recently_used_beyond_its_bytes():
    calls = []
    cache = PreparedCache(lambda features: calls.append(features["name"]) or Sized(40), max_bytes=100)
    for name in ["a", "b", "a", "c"]:  # a is used again before c arrives, so b is dropped
        cache.get(name, {"name": name})
    assert calls == ["a", "b", "c"] and len(cache) == 2
    cache.get("a", {"name": "a"})
    cache.get("b", {"name": "b"})
    assert calls == ["a", "b", "c", "b"]


def test_prepared_cache_keeps_one_state_larger_than_its_budget_and_none_states():
    cache = PreparedCache(lambda features: None if features["empty"] else Sized(500), max_bytes=100)
    assert cache.get("big", {"empty": False}).nbytes() == 500 and len(cache) == 1
    assert cache.get("empty", {"empty": True}) is None
    assert len(cache) == 1  # the big one went: over budget with two entries


def test_prepared_cache_prepares_each_image_once_for_many_threads():
    lock, calls = threading.Lock(), []

    def prepare(features):
        with lock:
            calls.append(features["name"])
        time.sleep(0.01)  # keep others asking for it while it is being prepared
        return Sized(1)

    cache = PreparedCache(prepare, max_bytes=1000)
    names = [f"image{i % 7}" for i in range(200)]
    with ThreadPoolExecutor(4) as pool:
        states = list(pool.map(lambda n: cache.get(n, {"name": n}), names))
    assert sorted(calls) == sorted(set(names)) and len(cache) == 7
    for name, state in zip(names, states):
        assert cache.get(name, {"name": name}) is state


def test_prepared_cache_hands_an_error_to_every_waiting_thread_and_retries_later():
    started, release, attempts = threading.Event(), threading.Event(), []

    def prepare(features):
        attempts.append(1)
        if len(attempts) == 1:
            started.set()
            release.wait(60)
            raise ValueError("bad descriptors in image0")
        return Sized(1)

    waiting = threading.Event()

    class SignallingPending(dict):
        """The cache's pending states; says when a second thread has found the first one's."""

        def get(self, key, default=None):
            found = super().get(key, default)
            if found is not None:
                waiting.set()
            return found

    cache = PreparedCache(prepare)
    cache._pending = SignallingPending()
    with ThreadPoolExecutor(2) as pool:
        first = pool.submit(cache.get, "image0", {})
        assert started.wait(60)
        second = pool.submit(cache.get, "image0", {})
        assert waiting.wait(60)  # the second thread holds the first one's pending state: it must wait on it
        release.set()
        for future in (first, second):
            with pytest.raises(ValueError, match="image0"):
                future.result()
    assert len(attempts) == 1 and len(cache) == 0
    assert cache.get("image0", {}).nbytes() == 1 and len(attempts) == 2


# ------------------------------------------------------- fused cross-attention --
# A true pair (LightGlue runs deep and prunes), a near one and a false one (it stops early).
SDPA_IMAGES = ["night_right/Image060.jpg", "day_right/Image060.jpg", "day_right/Image063.jpg", "day_right/Image140.jpg"]


@pytest.fixture(scope="module")
def xfeat_features(shared_data):
    return features_of(shared_data, "xfeat-lg", SDPA_IMAGES)


def reference_messages(query_key0, query_key1, value0, value1):
    """Bidirectional attention written out: softmax over keys of q.k, for each direction."""
    sim = query_key0 @ query_key1.transpose(-1, -2)
    return F.softmax(sim, -1) @ value1, F.softmax(sim.transpose(-1, -2), -1) @ value0


@pytest.mark.parametrize("attention", lightglue_prepared.CROSS_ATTENTIONS)
def test_cross_messages_equal_written_out_attention(attention):
    generator = torch.Generator().manual_seed(0)
    query_key0, value0 = torch.randn(2, 1, 4, 37, 64, generator=generator)
    query_key1, value1 = torch.randn(2, 1, 4, 53, 64, generator=generator)
    expected = reference_messages(query_key0, query_key1, value0, value1)
    found = lightglue_prepared._cross_messages(query_key0, query_key1, value0, value1, attention)
    for message, reference in zip(found, expected):
        torch.testing.assert_close(message, reference, rtol=1e-5, atol=1e-5)


@pytest.mark.slow
@pytest.mark.real_data
def test_sdpa_matches_agree_with_kornia_on_real_pairs(xfeat_features):
    conf, features = xfeat_features
    kornia = matchers.build_matcher(conf["matcher"], torch.device("cpu"))
    sdpa = matchers.build_matcher({**conf["matcher"], "cross_attention": "sdpa"}, torch.device("cpu"))
    prepared = [kornia.prepare(f) for f in features]
    for first, second in [(0, 1), (0, 2), (0, 3)]:
        matches, scores = kornia.match_prepared(prepared[first], prepared[second])
        sdpa_matches, sdpa_scores = sdpa.match_prepared(prepared[first], prepared[second])
        assert len(matches) > 10 or (first, second) == (0, 3)
        shared = {tuple(m) for m in matches} & {tuple(m) for m in sdpa_matches}
        # Rounding may move a match across the filter threshold, never more than a few.
        assert len(shared) >= 0.98 * max(len(matches), len(sdpa_matches))


def test_unknown_cross_attention_is_named():
    conf = methods.resolve_method("disk-lg", "repository")["matcher"]
    with pytest.raises(ValueError, match="unknown cross_attention 'flash'.*kornia, sdpa"):
        matchers.build_matcher({**conf, "cross_attention": "flash"}, torch.device("cpu"))
