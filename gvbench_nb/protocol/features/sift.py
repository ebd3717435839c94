"""SIFT: COLMAP's through pycolmap (the paper's, hloc's ``dog`` extractor) and OpenCV's."""

from __future__ import annotations

import threading
from typing import Any

import cv2
import numpy as np
import torch

from gvbench_nb.protocol.features.base import Extractor, Features, empty_features, to_uint8


def root_sift(descriptors: np.ndarray, eps: float = 1e-6) -> np.ndarray:
    """hloc's ``sift_to_rootsift`` (extractors/dog.py): L1-normalise, square root (clipped
    at ``eps``), L2-normalise, each with ``eps`` added to the norm."""
    descriptors = descriptors / (np.abs(descriptors).sum(axis=-1, keepdims=True) + eps)
    descriptors = np.sqrt(np.maximum(descriptors, eps))
    return descriptors / (np.linalg.norm(descriptors, axis=-1, keepdims=True) + eps)


class ColmapSiftExtractor(Extractor):
    """COLMAP's SIFT through pycolmap, as hloc's ``dog`` extractor with its ``sift`` conf: the image
    scaled to [0, 1], zero scores (COLMAP gives none), and hloc's own RootSIFT step applied again
    to pycolmap's RootSIFT descriptors ("COLMAP does not normalize well"). CPU unless pycolmap
    has CUDA and the device is CUDA, as hloc chooses."""

    type = "colmap_sift"

    def __init__(self, conf: dict[str, Any], device: torch.device):
        import warnings

        import pycolmap

        self.conf = conf
        options = pycolmap.SiftExtractionOptions()
        options.first_octave = conf["first_octave"]
        options.peak_threshold = conf["peak_threshold"]
        options.max_num_features = conf["max_keypoints"]
        options.normalization = (
            pycolmap.Normalization.L1_ROOT if conf.get("root_sift", True) else pycolmap.Normalization.L2
        )
        use_gpu = pycolmap.has_cuda and device.type == "cuda"
        with warnings.catch_warnings():  # pycolmap 4 deprecates Sift, the class hloc uses
            warnings.simplefilter("ignore", DeprecationWarning)
            self.sift = pycolmap.Sift(
                options=pycolmap.FeatureExtractionOptions(sift=options),
                device=pycolmap.Device.cuda if use_gpu else pycolmap.Device.cpu,
            )
        self._lock = threading.Lock()  # one extractor object, several workers: one image at a time

    def __call__(self, image: np.ndarray) -> Features:
        if image.ndim != 2:
            raise ValueError(
                f"COLMAP SIFT needs a grayscale image, got shape {image.shape}; "
                "set 'grayscale': True in the extractor conf"
            )
        normalised = np.ascontiguousarray(image.astype(np.float32) / np.float32(255.0))
        with self._lock:
            keypoints, descriptors = self.sift.extract(normalised)
        if len(keypoints) == 0:
            return empty_features(128)
        if self.conf.get("root_sift", True):
            descriptors = root_sift(descriptors)
        return {
            "keypoints": np.ascontiguousarray(keypoints[:, :2], dtype=np.float32),
            "scores": np.zeros(len(keypoints), np.float32),
            "descriptors": np.ascontiguousarray(descriptors, dtype=np.float32),
        }


class OpenCVSiftExtractor(Extractor):
    """OpenCV SIFT (not the paper's: it upsamples first); COLMAP's peak threshold maps to
    contrastThreshold = peak_threshold * nOctaveLayers, as OpenCV divides by the layers."""

    type = "opencv_sift"

    def __init__(self, conf: dict[str, Any], device: torch.device):
        self.conf = conf
        layers = 3
        # SIFT.create is SIFT_create; OpenCV's stubs type only the class method.
        self.sift = cv2.SIFT.create(
            nfeatures=conf["max_keypoints"], nOctaveLayers=layers, contrastThreshold=conf["peak_threshold"] * layers
        )

    def __call__(self, image: np.ndarray) -> Features:
        keypoints, descriptors = self.sift.detectAndCompute(to_uint8(image), None)
        if descriptors is None or not keypoints:
            return empty_features(128)
        points = np.array([kp.pt for kp in keypoints], dtype=np.float32)
        scores = np.array([kp.response for kp in keypoints], dtype=np.float32)
        values = descriptors.astype(np.float32)
        if self.conf.get("root_sift", True):
            # RootSIFT: L1-normalise, then square root (Arandjelovic & Zisserman 2012); unit L2 after.
            values /= np.maximum(np.abs(values).sum(axis=1, keepdims=True), 1e-8)
            values = np.sqrt(values)
        return {"keypoints": points, "scores": scores, "descriptors": values}
