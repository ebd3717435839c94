"""Shared fixtures: where the real data and the reference layouts are.

The real data is found through the package's data folder (``$GVBENCH_DATA``, else the
per-user cache): tests that need it skip with the ``data fetch`` command that fills it.
``make test`` runs that command first, from ../shared/data when that folder exists.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import pytest

PROJECT_ROOT = Path(__file__).resolve().parent.parent


def _first_dir(*candidates: Path | None) -> Path | None:
    return next((c for c in candidates if c is not None and c.is_dir()), None)


REAL_DATASETS = ("gvbench-lists", "gardens_point")


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """The data folder, holding every file of gardens_point/ and gvbench_gt/ (sizes checked)."""
    from gvbench_nb import data

    root = data.data_dir()
    datasets, _ = data.load_manifest()
    incomplete = [name for name in REAL_DATASETS if data.presence(datasets[name], root)[0] != len(datasets[name].files)]
    if incomplete:
        pytest.skip(f"real data not found in {root} ({', '.join(incomplete)}): run "
                    f"`python -m gvbench_nb data fetch {' '.join(REAL_DATASETS)}` (offline: add --mirror DIR)")
    return root


@pytest.fixture(scope="session")
def reference_dir() -> Path:
    """``$GVBENCH_REFERENCE`` or ``<repo>/../shared/reference`` (holding ``layouts/``)."""
    env = os.environ.get("GVBENCH_REFERENCE")
    found = _first_dir(Path(env) if env else None, PROJECT_ROOT.parent / "shared" / "reference")
    if found is None or not (found / "layouts").is_dir():
        pytest.skip("reference layouts not found: set GVBENCH_REFERENCE to the folder holding layouts/")
    return found


@pytest.fixture
def empty_hub(tmp_path, monkeypatch) -> Path:
    """Point the torch hub cache at an empty folder: no checkpoint is present.
    Yields the checkpoints folder a missing file should be put in."""
    import torch

    old = torch.hub.get_dir()
    torch.hub.set_dir(str(tmp_path / "hub"))
    monkeypatch.setenv("TORCH_HOME", str(tmp_path / "hub"))
    yield tmp_path / "hub" / "checkpoints"
    torch.hub.set_dir(old)


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
    import numpy as np

    o0 = rng.uniform([0, 0], [640, 480], (n_outliers, 2))
    o1 = rng.uniform([0, 0], [640, 480], (n_outliers, 2))
    order = rng.permutation(len(p0) + n_outliers)
    truth = np.r_[np.ones(len(p0), bool), np.zeros(n_outliers, bool)][order]
    return np.r_[p0, o0][order], np.r_[p1, o1][order], truth
