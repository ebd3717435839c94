"""Doppelgangers classifier (Cai et al., ICCV 2023) as a loop-closure verifier: a 10-channel input
in image 1's resized frame, zero-padded square (MODELS.md section 6): keypoints and F-RANSAC matches
of both images, image 1 and warped image 0. Departures only where the release crashes: identity
warp fallback, square side the largest of both images, unwarped indices clipped."""

from __future__ import annotations

import logging
import os
import time
from collections.abc import Mapping

import cv2
import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F

from gvbench_nb.protocol import weights

log = logging.getLogger(__name__)

CHECKPOINT_NAME = "doppelgangers_classifier_loftr"
INPUT_CHANNELS = 10
DIVISOR = 8  # LoFTR's stride: both sides are floored to a multiple of it
MATCH_CONFIDENCE = 0.8  # matches above this enter the F-RANSAC (original value)
F_RANSAC_THRESHOLD = 3.0
F_RANSAC_CONFIDENCE = 0.99
AFFINE_RANSAC_THRESHOLD = 20.0


class DoppelgangersClassifier(nn.Module):
    """conv 7x7/2 (10 -> 128), three stages of two BasicBlocks (128/256/512), average pool, linear
    512 -> 2; total stride 16, logits[:, 1] is "same place"."""

    def __init__(self) -> None:
        # LoFTR's ResNet basic block: its attribute order is the checkpoint's tensor order.
        from kornia.feature.loftr.backbone.resnet_fpn import BasicBlock

        super().__init__()
        self.conv1 = nn.Conv2d(INPUT_CHANNELS, 128, kernel_size=7, stride=2, padding=3, bias=False)
        self.bn1 = nn.BatchNorm2d(128)
        self.relu = nn.ReLU(inplace=True)
        dims = (128, 128, 256, 512)  # layer1..layer3, each of two BasicBlocks, the first halving
        self.layer1, self.layer2, self.layer3 = (
            nn.Sequential(BasicBlock(cin, cout, stride=2), BasicBlock(cout, cout)) for cin, cout in zip(dims, dims[1:])
        )
        self.fc = nn.Linear(dims[3], 2)
        self._init_weights()

    def _init_weights(self) -> None:
        # LoFTR's backbone initialisation: He (fan_out) for convs, BN as identity.
        for m in self.modules():
            if isinstance(m, nn.Conv2d):
                nn.init.kaiming_normal_(m.weight, mode="fan_out", nonlinearity="relu")
            elif isinstance(m, nn.BatchNorm2d):
                nn.init.ones_(m.weight)
                nn.init.zeros_(m.bias)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """(B, 10, H, W) -> logits (B, 2)."""
        x = self.relu(self.bn1(self.conv1(x)))
        x = self.layer3(self.layer2(self.layer1(x)))
        return self.fc(x.mean(dim=(2, 3)))  # global average pool (padding included)


def load_doppelgangers(
    path: str | os.PathLike[str] | None = None, device: str | torch.device = "cpu"
) -> DoppelgangersClassifier:
    """The classifier with the official weights, in eval mode; the file is the trainer's dict whose
    ``dec`` entry is a ``DataParallel`` state dict (``module.`` prefix). Missing -> ``MissingWeightsError``."""
    if path is None:
        path = weights.require(CHECKPOINT_NAME)[0]
    elif not os.path.isfile(path):
        raise weights.MissingWeightsError(f"{path} does not exist.\n" + weights.missing_message(CHECKPOINT_NAME))
    checkpoint = weights.load_checkpoint(path)
    state = checkpoint["dec"] if isinstance(checkpoint, Mapping) and "dec" in checkpoint else checkpoint
    state = {(k[len("module.") :] if k.startswith("module.") else k): v for k, v in state.items()}
    model = DoppelgangersClassifier()
    weights.load_state_dict_strict(model, state, str(path))
    return model.eval().to(device)


def resized_size(width: int, height: int, size: int = 1024, divisor: int = DIVISOR) -> tuple[int, int]:
    """(w, h) after scaling the longest side to ``size`` (rounded) and flooring both
    sides to a multiple of ``divisor`` (at least ``divisor``), as the original does."""
    scale = size / max(width, height)
    w, h = int(round(width * scale)), int(round(height * scale))
    return max(w // divisor * divisor, divisor), max(h // divisor * divisor, divisor)


def to_resized_frame(points: np.ndarray, original_wh: tuple[int, int], new_wh: tuple[int, int]) -> np.ndarray:
    """Map (N, 2) original pixels to the resized image, pixel centres aligned ((k + 0.5) * s - 0.5),
    so a matcher run at this frame round-trips exactly."""
    s = np.array([new_wh[0] / original_wh[0], new_wh[1] / original_wh[1]], dtype=np.float64)
    return (np.asarray(points, dtype=np.float64).reshape(-1, 2) + 0.5) * s - 0.5


def match_mask(
    keypoints0: np.ndarray, keypoints1: np.ndarray, confidence: np.ndarray, threshold: float = MATCH_CONFIDENCE
) -> np.ndarray:
    """(M,) bool: confidence > ``threshold`` and inlier of ``cv2.findFundamentalMat(FM_RANSAC, 3,
    0.99)`` in the classifier's resized frame, as the original selects; no model -> all False."""
    kp0 = np.asarray(keypoints0, dtype=np.float32).reshape(-1, 2)
    kp1 = np.asarray(keypoints1, dtype=np.float32).reshape(-1, 2)
    keep = np.asarray(confidence, dtype=np.float64).reshape(-1) > threshold
    out = np.zeros(len(kp0), dtype=bool)
    if keep.sum() == 0:
        return out
    try:
        fmat, inliers = cv2.findFundamentalMat(
            kp0[keep], kp1[keep], cv2.FM_RANSAC, F_RANSAC_THRESHOLD, F_RANSAC_CONFIDENCE
        )
    except cv2.error:
        return out
    if fmat is None or inliers is None:
        return out
    out[np.flatnonzero(keep)[inliers.ravel() == 1]] = True
    return out


def estimate_warp(keypoints0: np.ndarray, keypoints1: np.ndarray) -> np.ndarray | None:
    """2x3 similarity mapping image 0's resized frame onto image 1's, fitted by
    ``cv2.estimateAffinePartial2D`` (RANSAC, 20 px) on the given matched points;
    ``None`` when it cannot be fitted (the caller then uses the identity)."""
    src = np.asarray(keypoints0, dtype=np.float32).reshape(-1, 1, 2)
    dst = np.asarray(keypoints1, dtype=np.float32).reshape(-1, 1, 2)
    if len(src) < 2:
        return None
    try:
        warp, _ = cv2.estimateAffinePartial2D(
            src, dst, method=cv2.RANSAC, ransacReprojThreshold=AFFINE_RANSAC_THRESHOLD
        )
    except cv2.error:
        return None
    if warp is None or not np.all(np.isfinite(warp)):
        return None
    return warp


def _pixel_index(values: np.ndarray, limit: int) -> np.ndarray:
    """floor(v) clipped to [0, limit - 1]: the pixel a coordinate falls in."""
    return np.clip(np.floor(values), 0, limit - 1).astype(np.int64)


def _as_bgr(image: np.ndarray) -> np.ndarray:
    image = np.asarray(image, dtype=np.float32)
    if image.ndim != 3 or image.shape[2] != 3:
        raise ValueError(f"expected an (H, W, 3) BGR image, got shape {image.shape}")
    return image


def build_input(
    image0_bgr: np.ndarray,
    image1_bgr: np.ndarray,
    keypoints0: np.ndarray,
    keypoints1: np.ndarray,
    confidence: np.ndarray,
    size: int = 1024,
) -> np.ndarray:
    """The classifier's (10, S, S) float32 input for one pair (S = max resized side): BGR images,
    matched points in original pixels with their ``confidence`` (``match_mask`` picks the matches).
    Image 0 is warped onto image 1 unless the warp fails or lands outside."""
    img0, img1 = _as_bgr(image0_bgr), _as_bgr(image1_bgr)
    h0, w0 = img0.shape[:2]
    h1, w1 = img1.shape[:2]
    nw0, nh0 = resized_size(w0, h0, size)
    nw1, nh1 = resized_size(w1, h1, size)
    side = max(nw0, nh0, nw1, nh1)

    kp0 = to_resized_frame(keypoints0, (w0, h0), (nw0, nh0))
    kp1 = to_resized_frame(keypoints1, (w1, h1), (nw1, nh1))
    conf = np.asarray(confidence, dtype=np.float32).reshape(-1)
    if not (len(kp0) == len(kp1) == len(conf)):
        raise ValueError(f"keypoints0 {len(kp0)}, keypoints1 {len(kp1)} and confidence {len(conf)} differ in length")
    matched = match_mask(kp0, kp1, conf)

    # Warp image 0's keypoints into image 1's frame; keep those that land inside it.
    warp = estimate_warp(kp0[matched], kp1[matched]) if matched.any() else None
    if warp is not None:
        kp0_w = kp0 @ warp[:, :2].T + warp[:, 2]
        frame0 = (nw1, nh1)
        inside = (kp0_w[:, 0] >= 0) & (kp0_w[:, 0] < nw1) & (kp0_w[:, 1] >= 0) & (kp0_w[:, 1] < nh1)
        if not inside.any():
            warp = None  # nothing of image 0 would be visible: do not align (original)
    if warp is None:
        kp0_w, frame0 = kp0, (nw0, nh0)
        inside = (kp0[:, 0] >= 0) & (kp0[:, 0] < nw0) & (kp0[:, 1] >= 0) & (kp0[:, 1] < nh0)

    out = np.zeros((INPUT_CHANNELS, side, side), dtype=np.float32)
    # Channels 0/1: image 0's keypoints (confidence) and matches (1), warped.
    # Plain assignment: where several points share a pixel the last one wins, as in
    # the original.
    x0, y0 = _pixel_index(kp0_w[:, 0], frame0[0]), _pixel_index(kp0_w[:, 1], frame0[1])
    out[0, y0[inside], x0[inside]] = conf[inside]
    both = inside & matched
    out[1, y0[both], x0[both]] = 1.0
    # Channels 2/3: image 1's keypoints and matches, in its own frame.
    x1, y1 = _pixel_index(kp1[:, 0], nw1), _pixel_index(kp1[:, 1], nh1)
    out[2, y1, x1] = conf
    out[3, y1[matched], x1[matched]] = 1.0
    # Channels 4-6: image 1; 7-9: image 0 warped (bilinear; the original asked
    # warpAffine for INTER_AREA, which OpenCV treats as INTER_LINEAR).
    out[4:7, :nh1, :nw1] = cv2.resize(img1, (nw1, nh1)).transpose(2, 0, 1) / 255.0
    small0 = cv2.resize(img0, (nw0, nh0))
    if warp is not None:
        warped0 = cv2.warpAffine(small0, warp, (nw1, nh1), flags=cv2.INTER_LINEAR)
        out[7:10, :nh1, :nw1] = warped0.transpose(2, 0, 1) / 255.0
    else:
        out[7:10, :nh0, :nw0] = small0.transpose(2, 0, 1) / 255.0
    return out


def focal_loss(
    logits: torch.Tensor, targets: torch.Tensor, gamma: float = 1.0, alpha: float | None = None
) -> torch.Tensor:
    """Mean focal loss -alpha_t (1 - p_t)^gamma log p_t (Lin et al.) with the released trainer's
    defaults (gamma 1, no class weights); ``alpha`` a weighs the classes (a, 1 - a); (1 - p_t)
    is not differentiated, as in the original."""
    targets = targets.long().view(-1)
    logpt = F.log_softmax(logits, dim=1).gather(1, targets[:, None]).squeeze(1)
    pt = logpt.detach().exp()
    if alpha is not None:
        logpt = logpt * torch.tensor([alpha, 1 - alpha], dtype=logits.dtype, device=logits.device)[targets]
    return (-((1 - pt) ** gamma) * logpt).mean()


def train_classifier(
    model: nn.Module,
    inputs: np.ndarray | torch.Tensor,
    labels: np.ndarray | torch.Tensor,
    epochs: int = 20,
    lr: float = 5e-4,
    batch_size: int = 8,
    seed: int = 0,
    progress: bool = True,
) -> dict[str, list[float]]:
    """Train ``model`` in place by the released trainer's recipe (trainers/utils/utils.py: Adam at lr
    5e-4 for 20 epochs, focal loss, seeded shuffled batches); returns per-epoch ``{'loss',
    'accuracy', 'seconds'}`` lists."""
    x = torch.as_tensor(inputs, dtype=torch.float32)
    y = torch.as_tensor(labels).long().view(-1)
    if len(x) != len(y):
        raise ValueError(f"{len(x)} inputs but {len(y)} labels")
    device = next(model.parameters()).device
    optimiser = torch.optim.Adam(model.parameters(), lr=lr)
    generator = torch.Generator().manual_seed(seed)
    history: dict[str, list[float]] = {"loss": [], "accuracy": [], "seconds": []}
    model.train()
    for epoch in range(epochs):
        start = time.perf_counter()
        order = torch.randperm(len(x), generator=generator)
        total, correct = 0.0, 0
        for i in range(0, len(x), batch_size):
            idx = order[i : i + batch_size]
            xb, yb = x[idx].to(device), y[idx].to(device)
            optimiser.zero_grad()
            logits = model(xb)
            loss = focal_loss(logits, yb)
            loss.backward()
            optimiser.step()
            total += loss.item() * len(idx)
            correct += int((logits.argmax(1) == yb).sum())
        history["loss"].append(total / len(x))
        history["accuracy"].append(correct / len(x))
        history["seconds"].append(time.perf_counter() - start)
        if progress:
            log.info(
                "epoch %d/%d: loss %.4f acc %.3f (%.1f s)",
                *(epoch + 1, epochs, history["loss"][-1], history["accuracy"][-1], history["seconds"][-1]),
            )
    model.eval()
    return history


@torch.no_grad()
def predict(model: nn.Module, inputs: np.ndarray | torch.Tensor, batch_size: int = 4) -> np.ndarray:
    """P(same place) for (N, 10, S, S) inputs, in eval mode, batch by batch."""
    model.eval()
    device = next(model.parameters()).device
    x = torch.as_tensor(inputs, dtype=torch.float32)
    out = [F.softmax(model(x[i : i + batch_size].to(device)), dim=1)[:, 1].cpu() for i in range(0, len(x), batch_size)]
    return torch.cat(out).numpy() if out else np.zeros(0, dtype=np.float32)
