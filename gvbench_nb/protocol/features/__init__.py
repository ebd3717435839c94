"""Local feature extractors: one file a family, each class naming the recipe ``type`` it implements.

Adding an extractor is one file here with a subclass of ``base.Extractor`` (or a ``"module:Class"``
type in its conf for a class outside the package).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from gvbench_nb.protocol import registry

if TYPE_CHECKING:
    import torch

    from gvbench_nb.protocol.features.base import Extractor


def build_extractor(conf: dict[str, Any], device: torch.device) -> Extractor:
    from gvbench_nb.protocol.features.base import Extractor

    extractor: Extractor = registry.model_class("extractor type", Extractor, __name__, conf)(conf, device)
    return extractor
