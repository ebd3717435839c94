"""SuperPoint and SuperGlue: checkpoint layouts (read from the reference folder), post-processing
pieces, matching invariants; no weights needed."""

from __future__ import annotations

import math

import pytest
import torch
import torch.nn.functional as F
from helpers import random_state_dict, read_layout

from gvbench_nb.protocol import weights
from gvbench_nb.protocol.features import superpoint as sp
from gvbench_nb.protocol.matching import superglue as sg
from gvbench_nb.verification.doppelgangers import DoppelgangersClassifier, load_doppelgangers

MODELS = {
    "superpoint_v1": sp.SuperPoint,
    "superglue_outdoor": sg.SuperGlue,
    "doppelgangers_classifier_loftr": DoppelgangersClassifier,
}


@pytest.mark.parametrize(
    "name,count,renamed,dropped",
    [
        ("superpoint_v1", 24, "convDb.weight", "convPa.bias"),
        ("superglue_outdoor", 339, "gnn.layers.3.attn.merge.weight", "kenc.encoder.4.running_var"),
        ("doppelgangers_classifier_loftr", 98, "layer1.0.conv1.weight", "bn1.running_var"),
    ],
)
def test_state_dict_matches_official_layout_and_a_broken_one_names_the_bad_tensors(
    reference_dir, name, count, renamed, dropped
):
    layout = read_layout(reference_dir, name)
    ours = {k: list(v.shape) for k, v in MODELS[name]().state_dict().items()}
    assert len(layout) == count
    assert ours == layout and list(ours) == list(layout)  # same order too
    state = random_state_dict(layout)
    model = MODELS[name]()
    weights.load_state_dict_strict(model, state, f"synthetic {name}")
    assert torch.equal(model.state_dict()[renamed], state[renamed])
    state[renamed + "_renamed"] = state.pop(renamed)
    del state[dropped]
    with pytest.raises(weights.WeightsLayoutError) as err:
        weights.load_state_dict_strict(MODELS[name](), state, "broken.pth")
    for tensor in (renamed, renamed + "_renamed", dropped):
        assert tensor in str(err.value)


# ----------------------------------------------------------------------------- SuperPoint pieces


def test_cells_to_pixels_is_row_major_depth_to_space():
    x = torch.randn(2, 64, 3, 5)
    out = sp.cells_to_pixels(x)
    assert out.shape == (2, 24, 40)
    assert torch.equal(out, F.pixel_shuffle(x, 8)[:, 0])
    # channel k of cell (i, j) -> pixel (8i + k // 8, 8j + k % 8)
    assert out[1, 8 * 2 + 13 // 8, 8 * 4 + 13 % 8] == x[1, 13, 2, 4]


def test_nms_keeps_planted_maxima_and_suppresses_neighbours():
    r = 3
    s = torch.zeros(1, 40, 40)
    s[0, 10, 10] = 0.9  # A: global maximum
    s[0, 11, 12] = 0.5  # within r of A: suppressed
    s[0, 10, 13] = 0.8  # C: within r of A: suppressed
    s[0, 10, 16] = 0.7  # B: not a max of its window (C), but C dies -> kept by the 2nd pass
    s[0, 30, 30] = 0.6  # isolated maximum
    s[0, 33, 27] = 0.55  # at distance r (Chebyshev) of it: suppressed
    s[0, 30, 34] = 0.2  # at distance r + 1: a maximum of its own window
    out = sp.simple_nms(s, r)
    kept = {tuple(p) for p in torch.nonzero(out[0]).tolist()}
    assert kept == {(10, 10), (10, 16), (30, 30), (30, 34)}
    for y, x in kept:  # kept scores are unchanged
        assert out[0, y, x] == s[0, y, x]
    s = torch.rand(1, 9, 9)
    assert torch.equal(sp.simple_nms(s, 0), s)  # radius 0 keeps everything


def test_remove_borders():
    kpts = torch.tensor([[0, 10], [3, 10], [4, 10], [15, 10], [16, 10], [10, 3], [10, 4], [10, 25], [10, 26]])
    scores = torch.arange(len(kpts), dtype=torch.float)
    k, s = sp.remove_borders(kpts, scores, border=4, height=20, width=30)
    assert k.tolist() == [[4, 10], [15, 10], [10, 4], [10, 25]]
    assert s.tolist() == [2.0, 3.0, 6.0, 7.0]


def test_top_k_keeps_the_k_best():
    gen = torch.Generator().manual_seed(1)
    scores = torch.rand(50, generator=gen)
    kpts = torch.randint(0, 100, (50, 2), generator=gen)
    k, s = sp.top_k_keypoints(kpts, scores, 5)
    best = torch.argsort(scores, descending=True)[:5]
    assert torch.equal(s, scores[best])
    assert torch.equal(k, kpts[best])
    k_all, s_all = sp.top_k_keypoints(kpts, scores, 80)  # fewer than k: all, unchanged
    assert torch.equal(k_all, kpts) and torch.equal(s_all, scores)


def test_sample_descriptors_magic_leap_grid():
    h, w, s = 6, 10, 8
    rows, cols = torch.meshgrid(torch.arange(h, dtype=torch.float), torch.arange(w, dtype=torch.float), indexing="ij")
    # channel 0 = column index, channel 1 = row index, channel 2 = constant 100:
    # bilinear sampling of a linear map returns the fractional cell position.
    dense = torch.stack([cols, rows, torch.full_like(cols, 100.0)])[None]
    xy = torch.tensor([[3.5, 3.5], [79.0, 47.0], [20.0, 30.0], [41.25, 7.0]])
    out = sp.sample_descriptors(xy[None], dense, s)[0]  # (3, N)
    assert out.shape == (3, 4)
    assert torch.allclose(out.norm(dim=0), torch.ones(4), atol=1e-6)
    u = out[0] / out[2] * 100
    v = out[1] / out[2] * 100
    # Magic Leap: cell = (p - s/2 + 0.5) * (n - 1) / (n*s - s/2 - 0.5)
    exp_u = (xy[:, 0] - 3.5) * (w - 1) / (w * s - 4.5)
    exp_v = (xy[:, 1] - 3.5) * (h - 1) / (h * s - 4.5)
    assert torch.allclose(u, exp_u, atol=1e-4)
    assert torch.allclose(v, exp_v, atol=1e-4)
    assert u[0].item() == pytest.approx(0.0, abs=1e-5)  # pixel 3.5 = centre of cell 0
    assert u[1].item() == pytest.approx(9.0, abs=1e-4)  # last pixel w*s - 1 -> last column
    assert v[1].item() == pytest.approx(5.0, abs=1e-4)  # last pixel h*s - 1 -> last row


def test_superpoint_forward_random_weights():
    torch.manual_seed(0)
    model = sp.SuperPoint({"nms_radius": 3, "max_keypoints": 50, "keypoint_threshold": 0.0}).eval()
    image = torch.rand(2, 1, 100, 130)
    with torch.no_grad():
        out = model(image)
    assert len(out["keypoints"]) == 2
    with pytest.raises(ValueError):
        sp.SuperPoint({"max_keypoints": 0})
    for k, s, d in zip(out["keypoints"], out["scores"], out["descriptors"]):
        assert k.dtype == torch.float32 and k.shape[1] == 2
        assert 0 < len(k) <= 50
        assert s.shape == (len(k),) and d.shape == (len(k), 256)
        assert torch.allclose(d.norm(dim=1), torch.ones(len(k)), atol=1e-5)
        # x within [4, W8 - 4), y within [4, H8 - 4) where W8, H8 are floored to 8
        assert (k[:, 0] >= 4).all() and (k[:, 0] < 128 - 4).all()
        assert (k[:, 1] >= 4).all() and (k[:, 1] < 96 - 4).all()
        assert torch.all(s[:-1] >= s[1:])  # top-k cut: sorted
    # An image's keypoints do not depend on the batch it came in. Compared on the network's own
    # output, that cannot be exact: a batch of 2 (or another thread count) sums the convolutions
    # in another order, and random weights give near-uniform scores (here within 1e-5 of each
    # other, some tied) whose top-k then moves with the last bit. So: the dense maps agree up to
    # rounding, and the post-processing, given the batch's own maps, returns the batch's result
    # bit for bit (no state crosses from one image to the next).
    with torch.no_grad():
        features = model.encode(image)
        dense_scores, dense_descriptors = model.dense_scores(features), model.dense_descriptors(features)
        alone = model.encode(image[:1])
        assert torch.allclose(model.dense_scores(alone), dense_scores[:1], rtol=1e-4, atol=1e-7)
        assert torch.allclose(model.dense_descriptors(alone), dense_descriptors[:1], rtol=1e-4, atol=1e-6)
        for index in range(2):
            model.dense_scores = lambda _, i=index: dense_scores[i : i + 1]
            model.dense_descriptors = lambda _, i=index: dense_descriptors[i : i + 1]
            same = model({"image": image[index : index + 1]})
            for key in ("keypoints", "scores", "descriptors"):
                assert torch.equal(same[key][0], out[key][index]), key


@pytest.mark.parametrize(
    "load, checkpoint",
    [
        (sp.load_superpoint, "superpoint_v1"),
        (sg.load_superglue, "superglue_outdoor"),
        (load_doppelgangers, "doppelgangers_classifier_loftr"),
    ],
)
def test_loading_without_weights_names_file_url_and_place(empty_hub, load, checkpoint):
    with pytest.raises(weights.MissingWeightsError) as err:
        load()
    message, file = str(err.value), weights.CHECKPOINTS[checkpoint].file
    assert file in message and str(empty_hub / file) in message
    assert weights.CHECKPOINTS[checkpoint].urls[0] in message


# ----------------------------------------------------------------------------- SuperGlue pieces


def test_normalize_keypoints():
    kpts = torch.tensor([[[100.0, 50.0], [200.0, 50.0], [0.0, 0.0]]])
    out = sg.normalize_keypoints(kpts, (100, 200))  # (H, W)
    expected = torch.tensor([[[0.0, 0.0], [100 / 140, 0.0], [-100 / 140, -50 / 140]]])
    assert torch.allclose(out, expected)


@pytest.mark.parametrize("m,n", [(5, 7), (9, 3), (1, 1)])
def test_sinkhorn_marginals(m, n):
    gen = torch.Generator().manual_seed(m * 10 + n)
    scores = torch.randn(2, m, n, generator=gen) * 2
    alpha = torch.tensor(0.5)
    log_p = sg.log_optimal_transport(scores, alpha, iters=500)
    assert log_p.shape == (2, m + 1, n + 1)
    p = log_p.exp()
    rows, cols = p.sum(2), p.sum(1)
    # Each real row and column has mass 1; the dustbins take the rest: N and M.
    assert torch.allclose(rows[:, :m], torch.ones(2, m), atol=1e-4)
    assert torch.allclose(cols[:, :n], torch.ones(2, n), atol=1e-4)
    assert torch.allclose(rows[:, m], torch.full((2,), float(n)), atol=1e-3)
    assert torch.allclose(cols[:, n], torch.full((2,), float(m)), atol=1e-3)


def test_attention_splits_channels_dim_major_head_fastest():
    torch.manual_seed(0)
    attn = sg.MultiHeadedAttention(4, 256)
    x, src = torch.randn(1, 256, 11), torch.randn(1, 256, 13)
    # Reference: the release's view(b, dim, heads, n) split with explicit einsums.
    q, k, v = (layer(t).view(1, 64, 4, -1) for layer, t in zip(attn.proj, (x, src, src)))
    prob = torch.softmax(torch.einsum("bdhn,bdhm->bhnm", q, k) / 64**0.5, dim=-1)
    ref = attn.merge(torch.einsum("bhnm,bdhm->bdhn", prob, v).reshape(1, 256, -1))
    assert torch.allclose(attn(x, src, src), ref, atol=1e-5)


def random_inputs(n0: int, n1: int, b: int = 1, seed: int = 0) -> dict:
    gen = torch.Generator().manual_seed(seed)
    size = (480, 640)
    return {
        "keypoints0": torch.rand(b, n0, 2, generator=gen) * torch.tensor([640.0, 480.0]),
        "keypoints1": torch.rand(b, n1, 2, generator=gen) * torch.tensor([640.0, 480.0]),
        "scores0": torch.rand(b, n0, generator=gen),
        "scores1": torch.rand(b, n1, generator=gen),
        "descriptors0": F.normalize(torch.randn(b, n0, 256, generator=gen), dim=-1),
        "descriptors1": F.normalize(torch.randn(b, n1, 256, generator=gen), dim=-1),
        "image_size0": size,
        "image_size1": size,
    }


@pytest.fixture(scope="module")
def superglue_random() -> sg.SuperGlue:
    torch.manual_seed(0)
    return sg.SuperGlue({"sinkhorn_iterations": 50, "match_threshold": 0.0}).eval()


def test_superglue_forward_is_mutual(superglue_random):
    data = random_inputs(60, 45, b=2)
    with torch.no_grad():
        out = superglue_random(data)
    m0, m1 = out["matches0"], out["matches1"]
    assert m0.shape == (2, 60) and m1.shape == (2, 45)
    assert m0.dtype == torch.long
    assert out["matching_scores0"].shape == (2, 60)
    assert (m0 >= 0).any()  # threshold 0: every mutual argmax is a match
    for b in range(2):
        for i, j in enumerate(m0[b].tolist()):
            if j >= 0:
                assert m1[b, j].item() == i
                assert out["matching_scores1"][b, j] == out["matching_scores0"][b, i]
        for j, i in enumerate(m1[b].tolist()):
            if i >= 0:
                assert m0[b, i].item() == j
    # The batch is processed independently.
    single = {k: (v[1:] if torch.is_tensor(v) else v) for k, v in data.items()}
    with torch.no_grad():
        out1 = superglue_random(single)
    assert torch.equal(out1["matches0"][0], m0[1])


def test_mutual_matches_on_a_crafted_assignment():
    # 3 x 3 probabilities (+ dustbin row / column, ignored by the argmax).
    p = torch.tensor(
        [
            [0.90, 0.05, 0.00, 0.05],  # 0 <-> 0, mutual, 0.9
            [0.00, 0.15, 0.60, 0.25],  # 1 -> 2, but 2's best row is 2: not mutual
            [0.00, 0.10, 0.70, 0.20],  # 2 <-> 2, mutual, 0.7
            [0.10, 0.70, 0.40, 0.00],  # dustbin row
        ]
    )[None]
    out = sg.mutual_matches(p.clamp_min(1e-9).log(), threshold=0.2)
    assert out["matches0"].tolist() == [[0, -1, 2]]
    assert out["matches1"].tolist() == [[0, -1, 2]]
    assert torch.allclose(out["matching_scores0"], torch.tensor([[0.9, 0.0, 0.7]]))
    # Above the threshold only: 0.7 drops out, its score stays (as in the release).
    high = sg.mutual_matches(p.clamp_min(1e-9).log(), threshold=0.8)
    assert high["matches0"].tolist() == [[0, -1, -1]]
    assert high["matches1"].tolist() == [[0, -1, -1]]
    assert torch.allclose(high["matching_scores1"], torch.tensor([[0.9, 0.0, 0.7]]))


@pytest.mark.parametrize("n0,n1", [(0, 20), (20, 0), (0, 0)])
def test_superglue_zero_keypoints(superglue_random, n0, n1):
    with torch.no_grad():
        out = superglue_random(random_inputs(n0, n1))
    assert out["matches0"].shape == (1, n0) and out["matches1"].shape == (1, n1)
    assert (out["matches0"] == -1).all() and (out["matches1"] == -1).all()
    assert (out["matching_scores0"] == 0).all() and (out["matching_scores1"] == 0).all()


def test_superglue_default_conf():
    conf = sg.SuperGlue.default_conf
    assert conf["sinkhorn_iterations"] == 100 and conf["match_threshold"] == 0.2
    assert conf["GNN_layers"] == ["self", "cross"] * 9
    assert math.isclose(float(sg.SuperGlue().bin_score.detach()), 1.0)
