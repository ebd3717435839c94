"""Doppelgangers classifier: checkpoint loading, 10-channel input, training smoke (its layout:
test_superpoint_superglue.py)."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from helpers import random_state_dict, read_layout

from gvbench_nb.protocol.weights import MissingWeightsError, WeightsLayoutError
from gvbench_nb.verification.doppelgangers import (
    DoppelgangersClassifier,
    build_input,
    estimate_warp,
    focal_loss,
    load_doppelgangers,
    match_mask,
    predict,
    resized_size,
    to_resized_frame,
    train_classifier,
)


@pytest.fixture(scope="module")
def layout(reference_dir: Path) -> dict[str, list[int]]:
    return read_layout(reference_dir, "doppelgangers_classifier_loftr")


# --------------------------------------------------------------------------- weights


def test_loading_strips_the_module_prefix_and_names_a_missing_file_or_bad_tensors(layout, tmp_path):
    state = random_state_dict(layout)
    path = tmp_path / "doppelgangers_classifier_loftr.pt"
    torch.save({"dec": {"module." + k: v for k, v in state.items()}, "epoch": 20}, path)
    model = load_doppelgangers(path)
    assert not model.training
    loaded = model.state_dict()
    for k, v in state.items():
        assert torch.equal(loaded[k], v), k
    with torch.no_grad():
        assert model(torch.zeros(1, 10, 64, 64)).shape == (1, 2)
    with pytest.raises(MissingWeightsError, match="checkpoint.tar.gz"):  # the download is named
        load_doppelgangers(tmp_path / "nowhere.pt")
    del state["layer2.1.conv1.weight"]
    state["fc.weight"] = torch.zeros(3, 512)
    state["head.extra"] = torch.zeros(1)
    torch.save({"dec": state}, path)
    with pytest.raises(WeightsLayoutError) as info:
        load_doppelgangers(path)
    for name in ("layer2.1.conv1.weight", "fc.weight", "head.extra"):
        assert name in str(info.value)


# --------------------------------------------------------------------------- input


def texture(h: int, w: int, seed: int = 0) -> np.ndarray:
    """Smooth random BGR texture in 0..255 (smooth so bilinear resampling is faithful)."""
    rng = np.random.default_rng(seed)
    noise = rng.uniform(0, 255, (h, w, 3)).astype(np.float32)
    return np.clip(cv2.GaussianBlur(noise, (0, 0), 3) * 4 - 384, 0, 255).astype(np.uint8)


def grid(x0: float, x1: float, y0: float, y1: float, step: int) -> np.ndarray:
    xs, ys = np.meshgrid(np.arange(x0, x1, step), np.arange(y0, y1, step))
    return np.stack([xs.ravel(), ys.ravel()], 1).astype(np.float64)


def expected_masks(kp0_w, kp1, conf, matched, frame0, frame1, side):
    """Channels 0-3 rasterised independently: pixel floor(x, y) of each point."""
    masks = np.zeros((4, side, side), np.float32)
    inside = (kp0_w[:, 0] >= 0) & (kp0_w[:, 0] < frame0[0]) & (kp0_w[:, 1] >= 0) & (kp0_w[:, 1] < frame0[1])
    for (x, y), c, m, ok in zip(kp0_w, conf, matched, inside):
        if ok:
            masks[0, int(np.floor(y)), int(np.floor(x))] = c
            if m:
                masks[1, int(np.floor(y)), int(np.floor(x))] = 1
    for (x, y), c, m in zip(kp1, conf, matched):
        xi = min(max(int(np.floor(x)), 0), frame1[0] - 1)
        yi = min(max(int(np.floor(y)), 0), frame1[1] - 1)
        masks[2, yi, xi] = c
        if m:
            masks[3, yi, xi] = 1
    return masks


def test_translation_pair_masks_and_warp():
    h, w, t = 120, 160, np.array([12.0, 8.0])
    image0 = texture(h, w)
    image1 = np.zeros_like(image0)
    image1[8:, 12:] = image0[:-8, :-12]  # image 1 = image 0 moved by t
    kp0 = grid(20.5, 131, 20.5, 101, 10)  # pixel centres: floors are unambiguous
    kp1 = kp0 + t
    conf = np.linspace(0.81, 0.99, len(kp0)).astype(np.float32)
    conf[::5] = 0.5  # weak matches: keypoints, never "matches"

    out = build_input(image0, image1, kp0, kp1, conf, size=160)  # no resize: 160x120
    assert out.shape == (10, 160, 160) and out.dtype == np.float32

    matched = match_mask(kp0, kp1, conf)
    np.testing.assert_array_equal(matched, conf > 0.8)  # F-RANSAC keeps all consistent ones
    warp = estimate_warp(kp0[matched], kp1[matched])
    np.testing.assert_allclose(warp, [[1, 0, 12], [0, 1, 8]], atol=1e-4)

    # keypoints of image 0 land exactly on image 1's keypoints after the warp
    expected = expected_masks(kp0 + t, kp1, conf, matched, (w, h), (w, h), 160)
    np.testing.assert_array_equal(out[:4], expected)
    np.testing.assert_array_equal(out[0], out[2])
    np.testing.assert_array_equal(out[1], out[3])
    assert out[1].sum() == matched.sum() and out[0].max() == pytest.approx(conf.max())

    # warped image 0 equals image 1 where image 1 has content from image 0
    np.testing.assert_allclose(out[7:10, 8:h, 12:w], out[4:7, 8:h, 12:w], atol=2e-3)
    np.testing.assert_allclose(out[4:7, :h, :w], image1.transpose(2, 0, 1) / 255.0, atol=1e-6)
    assert np.all(out[:, h:, :] == 0)  # padding rows


def test_scale_and_resize_pair():
    H, W, size = 200, 320, 160  # resized to 160 x 100 -> floored to 160 x 96
    assert resized_size(W, H, size) == (160, 96)
    s, t = 1.25, np.array([-40.0, -25.0])  # zoom about the centre
    A = np.array([[s, 0, t[0]], [0, s, t[1]]])
    image0 = texture(H, W, seed=1)
    image1 = cv2.warpAffine(image0, A, (W, H), flags=cv2.INTER_LINEAR)
    kp0 = grid(60, 261, 40, 161, 13) + 0.3
    kp1 = kp0 * s + t
    conf = np.full(len(kp0), 0.9, np.float32)

    out = build_input(image0, image1, kp0, kp1, conf, size=size)
    assert out.shape == (10, 160, 160)

    r0 = to_resized_frame(kp0, (W, H), (160, 96))
    r1 = to_resized_frame(kp1, (W, H), (160, 96))
    np.testing.assert_allclose(r0[:, 0], (kp0[:, 0] + 0.5) * 0.5 - 0.5)
    np.testing.assert_allclose(r0[:, 1], (kp0[:, 1] + 0.5) * 0.48 - 0.5)
    warp = estimate_warp(r0, r1)
    np.testing.assert_allclose(warp[:, :2], s * np.eye(2), atol=1e-3)  # zoom survives the anisotropic resize
    kp0_w = r0 @ warp[:, :2].T + warp[:, 2]
    np.testing.assert_allclose(kp0_w, r1, atol=0.05)
    expected = expected_masks(kp0_w, r1, conf, np.ones(len(kp0), bool), (160, 96), (160, 96), 160)
    np.testing.assert_array_equal(out[:4], expected)

    # warped image 0 looks like image 1 (resampling differs), unlike unwarped image 0
    small0 = cv2.resize(image0.astype(np.float32), (160, 96)).transpose(2, 0, 1) / 255.0
    inner = (slice(None), slice(8, 88), slice(8, 152))
    aligned = np.abs(out[7:10][inner] - out[4:7][inner]).mean()
    unaligned = np.abs(small0[inner] - out[4:7][inner]).mean()
    assert aligned < 0.02 and aligned < unaligned / 4
    assert np.all(out[:, 96:, :] == 0)  # padding


def test_no_matches_means_identity():
    image0, image1 = texture(96, 128, 2), texture(96, 128, 3)
    kp = np.array([[10.5, 20.5], [50.5, 60.5], [100.5, 5.5]])
    conf = np.array([0.3, 0.6, 0.7], np.float32)  # nothing above 0.8
    out = build_input(image0, image1, kp, kp + 3, conf, size=128)
    assert out.shape == (10, 128, 128)
    assert out[1].sum() == 0 and out[3].sum() == 0
    np.testing.assert_allclose(out[7:10, :96, :128], image0.transpose(2, 0, 1) / 255.0, atol=1e-6)
    assert out[0, 20, 10] == pytest.approx(0.3) and out[2, 23, 13] == pytest.approx(0.3)
    assert np.count_nonzero(out[0]) == 3 and np.count_nonzero(out[2]) == 3


def test_match_mask_rejects_weak_and_outliers():
    rng = np.random.default_rng(0)
    X = np.c_[rng.uniform(-5, 5, (80, 2)), rng.uniform(8, 20, 80)]  # 3-D points
    K = np.array([[300.0, 0, 320], [0, 300, 240], [0, 0, 1]])
    R, _ = cv2.Rodrigues(np.array([0.0, 0.15, 0.02]))
    project = lambda P: (P @ K.T)[:, :2] / (P @ K.T)[:, 2:]
    p0, p1 = project(X), project(X @ R.T + [1.0, 0.1, 0.2])
    p1[:10] = rng.uniform(0, 640, (10, 2))  # gross outliers
    conf = np.full(80, 0.95)
    conf[10:20] = 0.6  # weak: excluded before RANSAC
    mask = match_mask(p0, p1, conf)
    assert not mask[10:20].any()
    assert mask[:10].sum() <= 1
    assert mask[20:].mean() > 0.95


# --------------------------------------------------------------------------- training


def test_focal_loss_reduces_to_cross_entropy():
    logits = torch.randn(6, 2, generator=torch.Generator().manual_seed(0))
    targets = torch.tensor([0, 1, 1, 0, 1, 0])
    ce = torch.nn.functional.cross_entropy(logits, targets)
    assert focal_loss(logits, targets, gamma=0.0) == pytest.approx(ce.item(), rel=1e-6)
    assert focal_loss(logits, targets, gamma=2.0) < focal_loss(logits, targets, gamma=1.0) < ce
    assert focal_loss(logits, targets, gamma=0.0, alpha=0.5) == pytest.approx(0.5 * ce.item(), rel=1e-6)


def toy_set(n: int = 8, side: int = 32):
    """Separable: positives have a dense match mask (channels 1/3), negatives none."""
    rng = np.random.default_rng(0)
    x = rng.uniform(0, 1, (n, 10, side, side)).astype(np.float32) * 0.2
    y = np.arange(n) % 2
    x[y == 1, 1] += 1.0
    x[y == 1, 3] += 1.0
    return x, y


@pytest.fixture
def one_thread():
    """One intra-op thread: on a shared 2-core machine a busy neighbour makes
    OpenMP's spinning threads ~10x slower; one thread is fast and reproducible."""
    old = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(old)


@pytest.mark.slow
def test_training_lowers_loss_and_is_deterministic(one_thread):
    x, y = toy_set()

    def run():
        torch.manual_seed(0)
        model = DoppelgangersClassifier()
        return model, train_classifier(model, x, y, epochs=3, lr=5e-4, batch_size=8, seed=3, progress=False)

    model, first = run()
    _, second = run()
    assert len(first["loss"]) == 3
    assert first["loss"][-1] < first["loss"][0]
    assert first["loss"] == second["loss"] and first["accuracy"] == second["accuracy"]
    assert not model.training
    p = predict(model, x)
    assert p.shape == (8,) and ((p >= 0) & (p <= 1)).all()
