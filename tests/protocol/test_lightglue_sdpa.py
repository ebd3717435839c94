"""LightGlue's cross-attention through torch's fused kernel (matcher conf ``cross_attention: sdpa``)."""

from __future__ import annotations

import pytest
import torch
import torch.nn.functional as F
from test_lightglue_prepared import features_of  # the shared real-image feature helper

from gvbench_nb import methods
from gvbench_nb.protocol import matching as matchers
from gvbench_nb.protocol.matching import lightglue_prepared

# A true pair (LightGlue runs deep and prunes), a near one and a false one (it stops early).
IMAGES = ["night_right/Image060.jpg", "day_right/Image060.jpg", "day_right/Image063.jpg", "day_right/Image140.jpg"]


@pytest.fixture(scope="module")
def xfeat_features(shared_data):
    return features_of(shared_data, "xfeat-lg", IMAGES)


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
