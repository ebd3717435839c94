"""Matchers: one file a family, chosen by ``conf['type']``.

A matcher is built as ``Class(conf, device)``. Sparse matchers are called on two feature
dicts, dense ones (class attribute ``dense = True``, no extractor in their method) on two
prepared images; ``matching/base.py`` says what each returns. Adding a matcher is one file
here and one line in ``MATCHER_TYPES`` (or a ``"module:Class"`` type in its conf).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING, Any

from gvbench_nb.protocol import registry

if TYPE_CHECKING:
    import torch

MATCHER_TYPES: dict[str, str] = {
    "nn": "gvbench_nb.protocol.matching.nearest_neighbour:NearestNeighbourMatcher",
    "kornia_lightglue": "gvbench_nb.protocol.matching.lightglue:LightGlueMatcher",
    "magicleap_superglue": "gvbench_nb.protocol.matching.superglue:SuperGlueMatcher",
    "kornia_loftr": "gvbench_nb.protocol.matching.loftr:LoFTRMatcher",
}


def build_matcher(conf: dict[str, Any], device: torch.device) -> Callable[..., Any]:
    kind = registry.resolve_type("matcher type", conf["type"], MATCHER_TYPES, f"matcher conf {conf.get('name', '?')!r}")
    matcher: Callable[..., Any] = kind(conf, device)
    return matcher
