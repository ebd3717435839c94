"""Local feature extractors: one file a family, each a ``base.Extractor`` subclass naming its
recipe ``type`` (or a ``"module:Class"`` type for a class outside the package)."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from gvbench_nb.protocol import registry

if TYPE_CHECKING:
    import torch

    from gvbench_nb.protocol.features.base import Extractor


def build_extractor(conf: dict[str, Any], device: torch.device) -> Extractor:
    from gvbench_nb.protocol.features.base import Extractor, torch_on_one_thread

    torch_on_one_thread()
    extractor: Extractor = registry.model_class("extractor type", Extractor, __name__, conf)(conf, device)
    return extractor
