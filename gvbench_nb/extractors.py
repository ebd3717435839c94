"""Local feature extractors, one small class a type, selected by ``conf['type']``.

Every extractor takes an image already prepared by ``images.load_for_extraction``
(grayscale uint8 (H, W) or RGB uint8 (H, W, 3)) and returns numpy arrays:
``keypoints`` (N, 2) float32 (x, y) in that image's pixels, ``scores`` (N,) float32,
``descriptors`` (N, D) float32 (uint8 for binary descriptors).
"""

from __future__ import annotations

from typing import Any, Callable

import cv2
import numpy as np
import torch

from . import weights

Features = dict[str, np.ndarray]


def resolve_device(device: str | torch.device | None = "auto") -> torch.device:
    if device in (None, "auto"):
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    return torch.device(device)


def _to_tensor(image: np.ndarray, device: torch.device) -> torch.Tensor:
    tensor = torch.from_numpy(np.ascontiguousarray(image)).float().div_(255.0)
    tensor = tensor[None, None] if tensor.ndim == 2 else tensor.permute(2, 0, 1)[None]
    return tensor.to(device)


class SiftExtractor:
    """OpenCV SIFT with RootSIFT descriptors.

    The paper's DoG peak threshold 0.01 (COLMAP's definition) maps to OpenCV's
    contrastThreshold = peak_threshold * nOctaveLayers, since OpenCV divides by the
    number of layers before comparing.
    """

    def __init__(self, conf: dict[str, Any], device: torch.device):
        self.conf = conf
        layers = 3
        self.sift = cv2.SIFT_create(
            nfeatures=conf["max_keypoints"],
            nOctaveLayers=layers,
            contrastThreshold=conf["peak_threshold"] * layers,
        )

    def __call__(self, image: np.ndarray) -> Features:
        keypoints, descriptors = self.sift.detectAndCompute(image, None)
        if descriptors is None or not keypoints:
            return _empty(128)
        points = np.array([kp.pt for kp in keypoints], dtype=np.float32)
        scores = np.array([kp.response for kp in keypoints], dtype=np.float32)
        descriptors = descriptors.astype(np.float32)
        if self.conf.get("root_sift", True):
            # RootSIFT: L1-normalise, then square root (Arandjelovic & Zisserman 2012); unit L2 after.
            descriptors /= np.maximum(np.abs(descriptors).sum(axis=1, keepdims=True), 1e-8)
            descriptors = np.sqrt(descriptors)
        return {"keypoints": points, "scores": scores, "descriptors": descriptors}


class OrbExtractor:
    """OpenCV ORB (the features ORB-SLAM verifies loop closures with); binary descriptors."""

    def __init__(self, conf: dict[str, Any], device: torch.device):
        self.orb = cv2.ORB_create(
            nfeatures=conf["max_keypoints"], scaleFactor=conf.get("scale_factor", 1.2), nlevels=conf.get("levels", 8),
            fastThreshold=conf.get("fast_threshold", 20),
        )

    def __call__(self, image: np.ndarray) -> Features:
        keypoints, descriptors = self.orb.detectAndCompute(image, None)
        if descriptors is None or not keypoints:
            return {**_empty(32), "descriptors": np.zeros((0, 32), np.uint8)}
        points = np.array([kp.pt for kp in keypoints], dtype=np.float32)
        scores = np.array([kp.response for kp in keypoints], dtype=np.float32)
        return {"keypoints": points, "scores": scores, "descriptors": descriptors.astype(np.uint8)}


class DiskExtractor:
    """kornia DISK (``depth`` weights), RGB, padded to a multiple of 16."""

    def __init__(self, conf: dict[str, Any], device: torch.device):
        from kornia.feature import DISK

        weights.require("disk_depth")
        self.conf, self.device = conf, device
        self.model = DISK.from_pretrained(conf.get("weights", "depth"), device=device).eval()

    @torch.inference_mode()
    def __call__(self, image: np.ndarray) -> Features:
        features = self.model(
            _to_tensor(image, self.device),
            n=self.conf["max_keypoints"],
            window_size=self.conf["nms_window"],
            score_threshold=self.conf["detection_threshold"],
            pad_if_not_divisible=True,
        )[0]
        return {
            "keypoints": features.keypoints.cpu().numpy().astype(np.float32),
            "scores": features.detection_scores.cpu().numpy().astype(np.float32),
            "descriptors": features.descriptors.cpu().numpy().astype(np.float32),
        }


class AlikedExtractor:
    """kornia ALIKED."""

    def __init__(self, conf: dict[str, Any], device: torch.device):
        from kornia.feature import ALIKED

        weights.require(*conf["checkpoints"])
        self.device = device
        self.model = ALIKED.from_pretrained(
            conf["model_name"], max_num_keypoints=conf["max_keypoints"],
            detection_threshold=conf["detection_threshold"], nms_radius=conf["nms_radius"], device=device,
        ).eval()

    @torch.inference_mode()
    def __call__(self, image: np.ndarray) -> Features:
        features = self.model(_to_tensor(image, self.device))[0]
        return {
            "keypoints": features.keypoints.cpu().numpy().astype(np.float32),
            "scores": features.keypoint_scores.cpu().numpy().astype(np.float32),
            "descriptors": features.descriptors.cpu().numpy().astype(np.float32),
        }


class XFeatExtractor:
    """kornia XFeat (sparse keypoints, 64-d descriptors)."""

    def __init__(self, conf: dict[str, Any], device: torch.device):
        from kornia.feature import XFeat

        weights.require(*conf["checkpoints"])
        self.conf, self.device = conf, device
        self.model = XFeat.from_pretrained(top_k=conf["max_keypoints"], detection_threshold=conf["detection_threshold"])
        self.model = self.model.to(device).eval()

    @torch.inference_mode()
    def __call__(self, image: np.ndarray) -> Features:
        output = self.model.detectAndCompute(_to_tensor(image, self.device))[0]
        return {
            "keypoints": output["keypoints"].cpu().numpy().astype(np.float32),
            "scores": output["scores"].cpu().numpy().astype(np.float32),
            "descriptors": output["descriptors"].cpu().numpy().astype(np.float32),
        }


class SuperPointExtractor:
    """Our SuperPoint (``models/superpoint.py``) on the official Magic Leap weights."""

    def __init__(self, conf: dict[str, Any], device: torch.device):
        from .models.superpoint import load_superpoint

        self.device = device
        model_conf = {k: conf[k] for k in ("nms_radius", "keypoint_threshold", "max_keypoints", "remove_borders")}
        self.model = load_superpoint(model_conf, device=device).eval()

    @torch.inference_mode()
    def __call__(self, image: np.ndarray) -> Features:
        output = self.model(_to_tensor(image, self.device))
        return {
            "keypoints": output["keypoints"][0].cpu().numpy().astype(np.float32),
            "scores": output["scores"][0].cpu().numpy().astype(np.float32),
            "descriptors": output["descriptors"][0].cpu().numpy().astype(np.float32),
        }


def _empty(dim: int) -> Features:
    return {
        "keypoints": np.zeros((0, 2), np.float32),
        "scores": np.zeros((0,), np.float32),
        "descriptors": np.zeros((0, dim), np.float32),
    }


EXTRACTOR_TYPES: dict[str, Callable[[dict[str, Any], torch.device], Callable[[np.ndarray], Features]]] = {
    "sift": SiftExtractor,
    "orb": OrbExtractor,
    "disk": DiskExtractor,
    "aliked": AlikedExtractor,
    "xfeat": XFeatExtractor,
    "superpoint": SuperPointExtractor,
}


def build_extractor(conf: dict[str, Any], device: torch.device) -> Callable[[np.ndarray], Features]:
    try:
        kind = EXTRACTOR_TYPES[conf["type"]]
    except KeyError:
        raise KeyError(f"unknown extractor type {conf['type']!r}; known: {', '.join(EXTRACTOR_TYPES)}") from None
    return kind(conf, device)
