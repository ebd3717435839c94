"""Helpers the tests share (fixtures stay in conftest.py)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest


def read_layout(reference_dir: Path, name: str) -> dict[str, list[int]]:
    """An official checkpoint's layout: tensor name -> shape ([] for scalars)."""
    path = reference_dir / "layouts" / f"{name}.layout.json"
    if not path.is_file():
        pytest.skip(f"missing {path}")
    return json.loads(path.read_text())


def random_state_dict(layout: dict[str, list[int]]) -> dict:
    """Random tensors in a layout, BatchNorm buffers valid (so a strict load can run)."""
    import torch

    generator = torch.Generator().manual_seed(0)
    state = {}
    for name, shape in layout.items():
        if name.endswith("num_batches_tracked"):
            state[name] = torch.tensor(7, dtype=torch.long)
        elif name.endswith("running_var"):
            state[name] = torch.rand(shape, generator=generator) + 0.5
        else:
            state[name] = torch.randn(shape, generator=generator)
    return state


def with_outlier_matches(rng, p0, p1, n_outliers: int):
    """Planted inlier matches (p0, p1) mixed with uniform random outlier matches in a
    640x480 image, shuffled. Returns points0, points1 and the true inlier mask."""

    o0 = rng.uniform([0, 0], [640, 480], (n_outliers, 2))
    o1 = rng.uniform([0, 0], [640, 480], (n_outliers, 2))
    order = rng.permutation(len(p0) + n_outliers)
    truth = np.r_[np.ones(len(p0), bool), np.zeros(n_outliers, bool)][order]
    return np.r_[p0, o0][order], np.r_[p1, o1][order], truth
