"""Matchers: one file a family, each a ``base.Matcher`` subclass naming its recipe ``type``
(or a ``"module:Class"`` type for a class outside the package)."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from gvbench_nb.protocol import registry

if TYPE_CHECKING:
    import torch

    from gvbench_nb.protocol.matching.base import Matcher


def build_matcher(conf: dict[str, Any], device: torch.device) -> Matcher:
    from gvbench_nb.protocol.features.base import torch_on_one_thread
    from gvbench_nb.protocol.matching.base import Matcher

    torch_on_one_thread()
    matcher: Matcher = registry.model_class("matcher type", Matcher, __name__, conf)(conf, device)
    return matcher
