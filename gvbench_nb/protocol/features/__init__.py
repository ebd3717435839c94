"""Local feature extractors: one file a family, chosen by ``conf['type']``.

Every extractor is built as ``Class(conf, device)`` and called on one prepared image; it
returns the feature dict described in ``features/base.py``. Adding an extractor is one file
here and one line in ``EXTRACTOR_TYPES`` (or a ``"module:Class"`` type in its conf).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING, Any

from gvbench_nb.protocol import registry

if TYPE_CHECKING:
    import numpy as np
    import torch

EXTRACTOR_TYPES: dict[str, str] = {
    "colmap_sift": "gvbench_nb.protocol.features.sift:ColmapSiftExtractor",
    "opencv_sift": "gvbench_nb.protocol.features.sift:OpenCVSiftExtractor",
    "opencv_orb": "gvbench_nb.protocol.features.orb:OrbExtractor",
    "kornia_disk": "gvbench_nb.protocol.features.disk:DiskExtractor",
    "kornia_aliked": "gvbench_nb.protocol.features.aliked:AlikedExtractor",
    "kornia_xfeat": "gvbench_nb.protocol.features.xfeat:XFeatExtractor",
    "magicleap_superpoint": "gvbench_nb.protocol.features.superpoint:SuperPointExtractor",
}


def build_extractor(conf: dict[str, Any], device: torch.device) -> Callable[[np.ndarray], dict[str, np.ndarray]]:
    kind = registry.resolve_type(
        "extractor type", conf["type"], EXTRACTOR_TYPES, f"extractor conf {conf.get('name', '?')!r}"
    )
    extractor: Callable[[np.ndarray], dict[str, np.ndarray]] = kind(conf, device)
    return extractor
