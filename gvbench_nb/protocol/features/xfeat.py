"""XFeat through kornia."""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

from gvbench_nb.protocol import weights
from gvbench_nb.protocol.features.base import Extractor, Features, as_features, to_tensor


class XFeatExtractor(Extractor):
    """kornia XFeat (sparse keypoints, 64-d descriptors)."""

    type = "kornia_xfeat"

    def __init__(self, conf: dict[str, Any], device: torch.device):
        from kornia.feature import XFeat

        weights.require(*conf["checkpoints"])
        self.conf, self.device = conf, device
        self.model = XFeat.from_pretrained(top_k=conf["max_keypoints"], detection_threshold=conf["detection_threshold"])
        self.model = self.model.to(device).eval()

    @torch.inference_mode()
    def __call__(self, image: np.ndarray) -> Features:
        output = self.model.detectAndCompute(to_tensor(image, self.device))[0]
        return as_features(output["keypoints"], output["scores"], output["descriptors"])
