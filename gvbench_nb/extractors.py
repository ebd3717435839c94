"""Local feature extractors, one small class a type, selected by ``conf['type']``.

Every extractor takes an image already prepared by ``images.load_for_extraction``
(grayscale (H, W) or RGB (H, W, 3), float32 in 0..255) and returns numpy arrays:
``keypoints`` (N, 2) float32 (x, y) in that image's pixels, ``scores`` (N,) float32,
``descriptors`` (N, D) float32 (uint8 for binary descriptors).
"""

from __future__ import annotations

import threading
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


def _to_uint8(image: np.ndarray) -> np.ndarray:
    """The 8-bit image OpenCV's detectors need (the prepared image is float after resizing)."""
    return image if image.dtype == np.uint8 else np.clip(np.rint(image), 0, 255).astype(np.uint8)


def root_sift(descriptors: np.ndarray, eps: float = 1e-6) -> np.ndarray:
    """hloc's ``sift_to_rootsift`` (extractors/dog.py): L1-normalise, square root (clipped
    at ``eps``), L2-normalise, each with ``eps`` added to the norm."""
    descriptors = descriptors / (np.abs(descriptors).sum(axis=-1, keepdims=True) + eps)
    descriptors = np.sqrt(np.maximum(descriptors, eps))
    return descriptors / (np.linalg.norm(descriptors, axis=-1, keepdims=True) + eps)


class ColmapSiftExtractor:
    """COLMAP's SIFT through pycolmap, as hloc's ``dog`` extractor with its ``sift`` conf.

    Options: first_octave, peak_threshold, RootSIFT normalisation (L1_ROOT), at most
    ``max_keypoints`` features (pycolmap's max_num_features, 8192 by default). hloc passes
    the float image scaled to [0, 1] and keeps x, y of each keypoint; its scores are zeros
    (COLMAP gives none). hloc then applies its own RootSIFT step to pycolmap's descriptors,
    which are RootSIFT already ("COLMAP does not normalize well"); so do we (``root_sift``).
    CPU unless pycolmap was built with CUDA and the device is CUDA, as hloc chooses.
    """

    def __init__(self, conf: dict[str, Any], device: torch.device):
        import warnings

        import pycolmap

        self.conf = conf
        options = pycolmap.SiftExtractionOptions()
        options.first_octave = conf["first_octave"]
        options.peak_threshold = conf["peak_threshold"]
        options.max_num_features = conf["max_keypoints"]
        options.normalization = pycolmap.Normalization.L1_ROOT if conf.get("root_sift", True) \
            else pycolmap.Normalization.L2
        use_gpu = pycolmap.has_cuda and device.type == "cuda"
        with warnings.catch_warnings():  # pycolmap 4 deprecates Sift, the class hloc uses
            warnings.simplefilter("ignore", DeprecationWarning)
            self.sift = pycolmap.Sift(options=pycolmap.FeatureExtractionOptions(sift=options),
                                      device=pycolmap.Device.cuda if use_gpu else pycolmap.Device.cpu)
        self._lock = threading.Lock()  # one extractor object, several workers: one image at a time

    def __call__(self, image: np.ndarray) -> Features:
        if image.ndim != 2:
            raise ValueError(f"COLMAP SIFT needs a grayscale image, got shape {image.shape}; "
                             "set 'grayscale': True in the extractor conf")
        normalised = np.ascontiguousarray(image.astype(np.float32) / np.float32(255.0))
        with self._lock:
            keypoints, descriptors = self.sift.extract(normalised)
        if len(keypoints) == 0:
            return _empty(128)
        if self.conf.get("root_sift", True):
            descriptors = root_sift(descriptors)
        return {
            "keypoints": np.ascontiguousarray(keypoints[:, :2], dtype=np.float32),
            "scores": np.zeros(len(keypoints), np.float32),
            "descriptors": np.ascontiguousarray(descriptors, dtype=np.float32),
        }


class OpenCVSiftExtractor:
    """OpenCV SIFT with RootSIFT descriptors (not the paper's SIFT: it upsamples first).

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
        keypoints, descriptors = self.sift.detectAndCompute(_to_uint8(image), None)
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
        keypoints, descriptors = self.orb.detectAndCompute(_to_uint8(image), None)
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
    "sift": ColmapSiftExtractor,
    "opencv_sift": OpenCVSiftExtractor,
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
