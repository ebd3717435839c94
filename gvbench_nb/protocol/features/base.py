"""What every extractor shares: its contract, the feature dict it returns, image tensors."""

from __future__ import annotations

from typing import ClassVar

import numpy as np
import torch

from gvbench_nb.protocol.registry import Model

Features = dict[str, np.ndarray]


class Extractor(Model):
    """Called on one image prepared by ``images.load_for_extraction`` (grayscale (H, W) or RGB
    (H, W, 3), float32 in 0..255); returns ``keypoints`` (N, 2) float32 (x, y) in that image's
    pixels, ``scores`` (N,) float32, ``descriptors`` (N, D) float32 (uint8 when binary)."""

    types: ClassVar[dict[str, type[Model]]] = {}

    def __call__(self, image: np.ndarray) -> Features:
        raise NotImplementedError


def torch_on_one_thread() -> None:
    """Run torch on one thread in this process: oneDNN's convolutions and MKL's products round
    differently on each thread count, so a model's output would depend on how the work was split.
    The cores are used by jobs side by side, each on one thread (docs/protocol.md: the cost)."""
    torch.set_num_threads(1)


def resolve_device(device: str | torch.device | None = "auto") -> torch.device:
    if device in (None, "auto"):
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    return torch.device(device)


def to_tensor(image: np.ndarray, device: torch.device) -> torch.Tensor:
    tensor = torch.from_numpy(np.ascontiguousarray(image)).float().div_(255.0)
    tensor = tensor[None, None] if tensor.ndim == 2 else tensor.permute(2, 0, 1)[None]
    return tensor.to(device)


def to_uint8(image: np.ndarray) -> np.ndarray:
    """The 8-bit image OpenCV's detectors need (the prepared image is float after resizing)."""
    return image if image.dtype == np.uint8 else np.clip(np.rint(image), 0, 255).astype(np.uint8)


def as_features(keypoints: torch.Tensor, scores: torch.Tensor, descriptors: torch.Tensor) -> Features:
    """The feature dict of a model's output tensors."""
    arrays = (t.cpu().numpy().astype(np.float32) for t in (keypoints, scores, descriptors))
    return dict(zip(("keypoints", "scores", "descriptors"), arrays))


def empty_features(dim: int) -> Features:
    return {
        "keypoints": np.zeros((0, 2), np.float32),
        "scores": np.zeros((0,), np.float32),
        "descriptors": np.zeros((0, dim), np.float32),
    }
