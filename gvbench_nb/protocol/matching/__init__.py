"""Matchers: one file a family, each class naming the recipe ``type`` it implements.

Adding a matcher is one file here with a subclass of ``base.Matcher`` (or a ``"module:Class"``
type in its conf for a class outside the package).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from gvbench_nb.protocol import registry

if TYPE_CHECKING:
    import torch

    from gvbench_nb.protocol.matching.base import Matcher


def build_matcher(conf: dict[str, Any], device: torch.device) -> Matcher:
    from gvbench_nb.protocol.matching.base import Matcher

    matcher: Matcher = registry.model_class("matcher type", Matcher, __name__, conf)(conf, device)
    return matcher
