"""LightGlue (and LighterGlue for XFeat) through kornia."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np
import torch

from gvbench_nb.protocol import weights
from gvbench_nb.protocol.matching.base import Matcher, Matches, empty_matches

if TYPE_CHECKING:  # kornia is imported when a matcher is built, not when this module is
    from gvbench_nb.protocol.matching.lightglue_prepared import PreparedImage


class LightGlueMatcher(Matcher):
    """kornia LightGlue (and LighterGlue for XFeat) with the paper's thresholds."""

    type = "kornia_lightglue"

    def __init__(self, conf: dict[str, Any], device: torch.device):
        from kornia.feature import LightGlue

        from gvbench_nb.protocol.matching import lightglue_prepared

        self._prepared = lightglue_prepared
        weights.require(*conf["checkpoints"])
        self.device = device
        options = {k: conf[k] for k in ("depth_confidence", "width_confidence", "filter_threshold") if k in conf}
        self.model = LightGlue(conf["features"], **options).to(device).eval()
        # The per-image part of LightGlue can be computed once per image (matching/lightglue_prepared.py);
        # that split reproduces the CPU path only.
        self.can_prepare = device.type == "cpu" and lightglue_prepared.supports_prepared(self.model)
        # 'kornia' (default): kornia's CPU cross-attention, bit-identical to LightGlue.forward.
        # 'sdpa': torch's fused attention kernel on that path, equal up to float rounding.
        # On CUDA kornia's own forward already attends through scaled_dot_product_attention.
        self.cross_attention = conf.get("cross_attention", "kornia")
        if self.cross_attention not in lightglue_prepared.CROSS_ATTENTIONS:
            raise ValueError(
                f"matcher {conf.get('name', conf['type'])!r}: unknown cross_attention "
                f"{self.cross_attention!r}; use one of {', '.join(lightglue_prepared.CROSS_ATTENTIONS)}"
            )
        if self.cross_attention == "sdpa" and device.type == "cpu" and not self.can_prepare:
            raise ValueError(
                f"matcher {conf.get('name', conf['type'])!r}: cross_attention 'sdpa' needs the prepared "
                "CPU path (no mixed precision, scale/orientation or LAF inputs); drop the option"
            )

    def _side(self, features: dict[str, np.ndarray]) -> dict[str, torch.Tensor]:
        return {
            "keypoints": torch.from_numpy(features["keypoints"]).float()[None].to(self.device),
            "descriptors": torch.from_numpy(features["descriptors"]).float()[None].to(self.device),
            "image_size": torch.from_numpy(features["image_size"]).float()[None].to(self.device),
        }

    @torch.inference_mode()
    def __call__(self, features0: dict[str, np.ndarray], features1: dict[str, np.ndarray]) -> Matches:
        if len(features0["keypoints"]) == 0 or len(features1["keypoints"]) == 0:
            return empty_matches()
        output = self.model({"image0": self._side(features0), "image1": self._side(features1)})
        return (
            output["matches"][0].cpu().numpy().astype(np.int64),
            output["scores"][0].cpu().numpy().astype(np.float32),
        )

    def prepare(self, features: dict[str, np.ndarray]) -> PreparedImage | None:
        """One image's LightGlue state before it meets the other image (None: no keypoints)."""
        if not self.can_prepare:
            raise RuntimeError(
                "this LightGlue cannot be prepared per image (CUDA, mixed precision or "
                "scale/orientation inputs); call the matcher on two feature dicts"
            )
        if len(features["keypoints"]) == 0:
            return None
        side = self._side(features)
        return self._prepared.prepare_image(self.model, side["keypoints"], side["descriptors"], side["image_size"])

    def match_prepared(self, prepared0: PreparedImage | None, prepared1: PreparedImage | None) -> Matches:
        """The same matches and scores as ``self(features0, features1)``, from ``prepare``'s states."""
        if prepared0 is None or prepared1 is None:
            return empty_matches()
        pair_matches, scores = self._prepared.match_prepared(self.model, prepared0, prepared1, self.cross_attention)
        return pair_matches.cpu().numpy().astype(np.int64), scores.cpu().numpy().astype(np.float32)
