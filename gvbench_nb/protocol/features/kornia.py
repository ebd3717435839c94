"""The extractors kornia implements: ALIKED, DISK, XFeat."""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

from gvbench_nb.protocol import weights
from gvbench_nb.protocol.features.base import Extractor, Features, as_features, to_tensor


class AlikedExtractor(Extractor):
    """kornia ALIKED."""

    type = "kornia_aliked"

    def __init__(self, conf: dict[str, Any], device: torch.device):
        from kornia.feature import ALIKED

        weights.require(*conf["checkpoints"])
        self.device = device
        self.model = ALIKED.from_pretrained(
            conf["model_name"],
            max_num_keypoints=conf["max_keypoints"],
            detection_threshold=conf["detection_threshold"],
            nms_radius=conf["nms_radius"],
            device=device,
        ).eval()

    @torch.inference_mode()
    def __call__(self, image: np.ndarray) -> Features:
        features = self.model(to_tensor(image, self.device))[0]
        return as_features(features.keypoints, features.keypoint_scores, features.descriptors)


class DiskExtractor(Extractor):
    """kornia DISK (``depth`` weights), RGB, padded to a multiple of 16."""

    type = "kornia_disk"

    def __init__(self, conf: dict[str, Any], device: torch.device):
        from kornia.feature import DISK

        weights.require("disk_depth")
        self.conf, self.device = conf, device
        self.model = DISK.from_pretrained(conf.get("weights", "depth"), device=device).eval()

    @torch.inference_mode()
    def __call__(self, image: np.ndarray) -> Features:
        features = self.model(
            to_tensor(image, self.device),
            n=self.conf["max_keypoints"],
            window_size=self.conf["nms_window"],
            score_threshold=self.conf["detection_threshold"],
            pad_if_not_divisible=True,
        )[0]
        return as_features(features.keypoints, features.detection_scores, features.descriptors)


class XFeatExtractor(Extractor):
    """kornia XFeat (sparse keypoints, 64-d descriptors)."""

    type = "kornia_xfeat"

    def __init__(self, conf: dict[str, Any], device: torch.device):
        from kornia.feature import XFeat

        weights.require(*conf["checkpoints"])
        self.device = device
        model = XFeat.from_pretrained(top_k=conf["max_keypoints"], detection_threshold=conf["detection_threshold"])
        self.model = model.to(device).eval()

    @torch.inference_mode()
    def __call__(self, image: np.ndarray) -> Features:
        output = self.model.detectAndCompute(to_tensor(image, self.device))[0]
        return as_features(output["keypoints"], output["scores"], output["descriptors"])
