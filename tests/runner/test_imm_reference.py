"""``imm:`` methods give vismatch's own matches (its ``load_image`` then ``_forward``), pair by pair,
on the first 10 pairs of ``params/gardens_point.yaml``; opt-in venv (``make test-reference``) only."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np
import pytest

from gvbench_nb import methods
from gvbench_nb.data.sequences import Sequence
from gvbench_nb.protocol.images import to_original_pixels
from gvbench_nb.runner import config, pair_matching, sequence_build

imm = methods.imm_peer()  # benchmarks/imm.py

PROJECT = Path(__file__).resolve().parents[2]
ENABLE = "make setup-imm && .venv-imm/bin/python -m pytest -m reference tests (make test-reference)"

pytestmark = [
    pytest.mark.reference,
    pytest.mark.real_data,
    pytest.mark.skipif(
        importlib.util.find_spec("vismatch") is None, reason=f"vismatch is not installed here; run: {ENABLE}"
    ),
]


@pytest.mark.parametrize("name", ["orb-nn", "sift-nn"])
def test_imm_methods_give_vismatchs_own_matches_pair_by_pair(shared_data, tmp_path, name):
    import torch
    from PIL import Image
    from vismatch import get_matcher

    params = config.load_params(PROJECT / "params" / "gardens_point.yaml", limit=10)
    root = Path(params["image_root"])
    sequence = Sequence("gardens_point", root, sequence_build.frame_tolerance_sequence_pairs(params)[:10])
    conf = methods.resolve_method(f"imm:{name}", "repository")
    pair_matching.match_and_verify(sequence, conf, tmp_path / "cache", progress=False)
    store = pair_matching.match_store(tmp_path / "cache", conf)

    theirs = get_matcher(name, device="cpu", max_num_keypoints=2048)
    width, height = conf["matcher"]["resize_to"]
    found = []
    for pair in sequence.pairs:
        paths = [root / pair.query, root / pair.reference]
        with torch.inference_mode():
            matched = theirs._forward(*(theirs.load_image(p, resize=(height, width)) for p in paths))
        entry = store.read(pair_matching.pair_key(root, pair.query, pair.reference, 0))
        for side, path in enumerate(paths):
            scale = np.array(Image.open(path).size, dtype=np.float32) / np.float32([width, height])
            expected = to_original_pixels(np.asarray(imm._numpy(matched[side]), dtype=np.float32), scale)
            np.testing.assert_allclose(entry[f"points{side}"], expected, rtol=0, atol=1e-3, err_msg=str(pair))
        found.append(len(entry["points0"]))
    assert sum(found) > 50  # matches to compare, not empty pairs
