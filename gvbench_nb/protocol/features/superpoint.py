"""SuperPoint (DeTone et al., CVPRW 2018) whose ``state_dict`` matches Magic Leap's
``superpoint_v1.pth`` (strict load); post-processing follows the Magic Leap release step by step,
as GV-Bench ran it through hloc. Weights: Magic Leap, non-commercial only."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor, nn

from gvbench_nb.protocol import weights
from gvbench_nb.protocol.features.base import Extractor, Features, as_features, to_tensor

CHECKPOINT = "superpoint_v1"


def cells_to_pixels(probs: Tensor, cell: int = 8) -> Tensor:
    """Depth to space: (B, cell*cell, h, w) -> (B, h*cell, w*cell); the 64 channels of a cell
    are an 8x8 patch in row-major order."""
    b, c, h, w = probs.shape
    if c != cell * cell:
        raise ValueError(f"expected {cell * cell} channels, got {c}")
    probs = probs.permute(0, 2, 3, 1).reshape(b, h, w, cell, cell)
    return probs.permute(0, 1, 3, 2, 4).reshape(b, h * cell, w * cell)


def simple_nms(scores: Tensor, nms_radius: int) -> Tensor:
    """Zero every score (B, H, W) that is not the maximum of its (2r+1)x(2r+1) window, with the
    Magic Leap code's two second-chance passes for points suppressed by a suppressed neighbour."""
    if nms_radius < 0:
        raise ValueError(f"nms_radius must be >= 0, got {nms_radius}")

    def max_pool(x: Tensor) -> Tensor:
        return F.max_pool2d(x, kernel_size=2 * nms_radius + 1, stride=1, padding=nms_radius)

    zeros = torch.zeros_like(scores)
    max_mask = scores == max_pool(scores)
    for _ in range(2):
        # Everything within the radius of a kept maximum is suppressed ...
        suppressed = max_pool(max_mask.float()) > 0
        remaining = torch.where(suppressed, zeros, scores)
        # ... and the maxima of what is left, outside that zone, are kept too.
        new_max_mask = remaining == max_pool(remaining)
        max_mask = max_mask | (new_max_mask & ~suppressed)
    return torch.where(max_mask, scores, zeros)


def remove_borders(keypoints: Tensor, scores: Tensor, border: int, height: int, width: int) -> tuple[Tensor, Tensor]:
    """Drop keypoints (N, 2) (row, col) closer than ``border`` pixels to the edge (the Magic Leap
    code removes borders before flipping to x, y)."""
    inside_y = (keypoints[:, 0] >= border) & (keypoints[:, 0] < height - border)
    inside_x = (keypoints[:, 1] >= border) & (keypoints[:, 1] < width - border)
    keep = inside_y & inside_x
    return keypoints[keep], scores[keep]


def top_k_keypoints(keypoints: Tensor, scores: Tensor, k: int) -> tuple[Tensor, Tensor]:
    """Keep the ``k`` best-scored keypoints: sorted by decreasing score when it cuts
    (``torch.topk``), input order otherwise, as in the original."""
    if k >= len(keypoints):
        return keypoints, scores
    scores, indices = torch.topk(scores, k, dim=0)
    return keypoints[indices], scores


def sample_descriptors(keypoints: Tensor, descriptors: Tensor, s: int = 8) -> Tensor:
    """Bilinearly sample (B, C, h, w) descriptors at (B, N, 2) (x, y) pixels -> (B, C, N), L2-normed.
    The pixel -> [-1, 1] mapping is Magic Leap's on purpose (hloc calls it slightly off): shift by
    s/2 - 0.5, divide by ``w*s - s/2 - 0.5``, ``align_corners=True`` (the release's intent)."""
    b, c, h, w = descriptors.shape
    keypoints = keypoints - s / 2 + 0.5
    keypoints = keypoints / keypoints.new_tensor([w * s - s / 2 - 0.5, h * s - s / 2 - 0.5])
    grid = keypoints * 2 - 1  # to (-1, 1)
    sampled = F.grid_sample(descriptors, grid.view(b, 1, -1, 2), mode="bilinear", align_corners=True)
    return F.normalize(sampled.reshape(b, c, -1), p=2, dim=1)


class SuperPoint(nn.Module):
    """SuperPoint with the official checkpoint's layout: grayscale (B, 1, H, W) in [0, 1] (or
    ``{"image": ...}``) -> per-image lists of ``keypoints`` (N, 2) (x, y), ``scores``, ``descriptors``
    (N, 256); only the top-left 8*floor(H/8) x 8*floor(W/8) part holds keypoints, as in the release."""

    default_conf: dict[str, Any] = {
        "descriptor_dim": 256,
        "nms_radius": 4,
        "keypoint_threshold": 0.005,
        "max_keypoints": -1,
        "remove_borders": 4,
    }

    def __init__(self, conf: Mapping[str, Any] | None = None) -> None:
        super().__init__()
        self.conf = {**self.default_conf, **(conf or {})}
        mk = self.conf["max_keypoints"]
        if mk == 0 or mk < -1:
            raise ValueError(f'"max_keypoints" must be positive or -1, got {mk}')

        self.relu = nn.ReLU(inplace=True)
        self.pool = nn.MaxPool2d(kernel_size=2, stride=2)
        # Shared VGG-style encoder: four blocks of two 3x3 convs (conv1a, conv1b, ..., conv4b),
        # pooling after blocks 1-3; registered in the release's order, which names its tensors.
        channels = (1, 64, 64, 128, 128)
        for block in range(1, 5):
            self.add_module(f"conv{block}a", nn.Conv2d(channels[block - 1], channels[block], 3, stride=1, padding=1))
            self.add_module(f"conv{block}b", nn.Conv2d(channels[block], channels[block], 3, stride=1, padding=1))
        c4, c5 = 128, 256

        # Detector head: 64 pixel positions of an 8x8 cell + 1 "no keypoint" bin.
        self.convPa = nn.Conv2d(c4, c5, kernel_size=3, stride=1, padding=1)
        self.convPb = nn.Conv2d(c5, 65, kernel_size=1, stride=1, padding=0)

        # Descriptor head: a semi-dense map at stride 8.
        self.convDa = nn.Conv2d(c4, c5, kernel_size=3, stride=1, padding=1)
        self.convDb = nn.Conv2d(c5, self.conf["descriptor_dim"], kernel_size=1, stride=1, padding=0)

    def encode(self, image: Tensor) -> Tensor:
        """Shared encoder: (B, 1, H, W) -> (B, 128, H/8, W/8)."""
        x = image
        for block in range(1, 5):
            x = self.relu(getattr(self, f"conv{block}a")(x))
            x = self.relu(getattr(self, f"conv{block}b")(x))
            x = self.pool(x) if block < 4 else x
        return x

    def dense_scores(self, features: Tensor) -> Tensor:
        """Detector head -> full-resolution keypoint probabilities (B, 8h, 8w), before NMS."""
        logits = self.convPb(self.relu(self.convPa(features)))
        probs = F.softmax(logits, dim=1)[:, :-1]  # drop the no-keypoint bin
        return cells_to_pixels(probs)

    def dense_descriptors(self, features: Tensor) -> Tensor:
        """Descriptor head -> L2-normalised (B, 256, h, w) map at stride 8."""
        desc = self.convDb(self.relu(self.convDa(features)))
        return F.normalize(desc, p=2, dim=1)

    def forward(self, image: Tensor | Mapping[str, Tensor]) -> dict[str, list[Tensor]]:
        if isinstance(image, Mapping):
            image = image["image"]
        if image.dim() != 4 or image.shape[1] != 1:
            raise ValueError(f"expected a grayscale batch (B, 1, H, W), got {tuple(image.shape)}")
        conf = self.conf

        features = self.encode(image)
        scores = simple_nms(self.dense_scores(features), conf["nms_radius"])
        height, width = scores.shape[-2:]

        keypoints_all: list[Tensor] = []
        scores_all: list[Tensor] = []
        for s in scores:
            kpts = torch.nonzero(s > conf["keypoint_threshold"])  # (N, 2) as (y, x)
            kpt_scores = s[kpts[:, 0], kpts[:, 1]]
            kpts, kpt_scores = remove_borders(kpts, kpt_scores, conf["remove_borders"], height, width)
            if conf["max_keypoints"] >= 0:
                kpts, kpt_scores = top_k_keypoints(kpts, kpt_scores, conf["max_keypoints"])
            keypoints_all.append(torch.flip(kpts, [1]).float())  # (y, x) -> (x, y)
            scores_all.append(kpt_scores)

        dense = self.dense_descriptors(features)
        descriptors_all = [sample_descriptors(k[None], d[None], 8)[0].t() for k, d in zip(keypoints_all, dense)]
        return {"keypoints": keypoints_all, "scores": scores_all, "descriptors": descriptors_all}


def load_superpoint(conf: Mapping[str, Any] | None = None, device: str | torch.device = "cpu") -> SuperPoint:
    """SuperPoint with the official ``superpoint_v1.pth`` weights, in eval mode; raises
    ``MissingWeightsError`` or ``WeightsLayoutError`` (see ``weights``)."""
    return weights.load_pretrained(SuperPoint(conf), CHECKPOINT, device)


class SuperPointExtractor(Extractor):
    """The SuperPoint above on the official Magic Leap weights."""

    type = "magicleap_superpoint"

    def __init__(self, conf: dict[str, Any], device: torch.device):
        self.device = device
        model_conf = {k: conf[k] for k in ("nms_radius", "keypoint_threshold", "max_keypoints", "remove_borders")}
        self.model = load_superpoint(model_conf, device=device)

    @torch.inference_mode()
    def __call__(self, image: np.ndarray) -> Features:
        output = self.model(to_tensor(image, self.device))
        return as_features(output["keypoints"][0], output["scores"][0], output["descriptors"][0])
