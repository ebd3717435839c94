"""ALIKED through kornia."""

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
