"""ORB through OpenCV."""

from __future__ import annotations

from typing import Any

import cv2
import numpy as np
import torch

from gvbench_nb.protocol.features.base import Extractor, Features, empty_features, to_uint8


class OrbExtractor(Extractor):
    """OpenCV ORB (the features ORB-SLAM verifies loop closures with); binary descriptors."""

    type = "opencv_orb"

    def __init__(self, conf: dict[str, Any], device: torch.device):
        # ORB.create is ORB_create; OpenCV's stubs type only the class method.
        self.orb = cv2.ORB.create(
            nfeatures=conf["max_keypoints"],
            scaleFactor=conf.get("scale_factor", 1.2),
            nlevels=conf.get("levels", 8),
            fastThreshold=conf.get("fast_threshold", 20),
        )

    def __call__(self, image: np.ndarray) -> Features:
        keypoints, descriptors = self.orb.detectAndCompute(to_uint8(image), None)
        if descriptors is None or not keypoints:
            return {**empty_features(32), "descriptors": np.zeros((0, 32), np.uint8)}
        points = np.array([kp.pt for kp in keypoints], dtype=np.float32)
        scores = np.array([kp.response for kp in keypoints], dtype=np.float32)
        return {"keypoints": points, "scores": scores, "descriptors": descriptors.astype(np.uint8)}
