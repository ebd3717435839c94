"""The reference tier: ours beside the reference code (vismatch 1.4.0's Magic Leap models, cvg's
LightGlue, image-matching-models' OpenCV matchers) on the same inputs; marker ``reference``, run by
``make test-reference`` (``make setup-imm && .venv-imm/bin/python -m pytest -m reference tests``)."""

from __future__ import annotations

import contextlib
import functools
import importlib.util
import math
import sys
import types
from pathlib import Path

import numpy as np
import pytest
import torch

from gvbench_nb import methods
from gvbench_nb.protocol import images

ENABLE = "make setup-imm && .venv-imm/bin/python -m pytest -m reference tests (make test-reference)"
VISMATCH = importlib.util.find_spec("vismatch")

pytestmark = [
    pytest.mark.reference,
    pytest.mark.skipif(
        VISMATCH is None,
        reason=f"the reference code (vismatch 1.4.0 and its third_party) is not installed here; run: {ENABLE}",
    ),
]


def third_party() -> Path:
    assert VISMATCH is not None and VISMATCH.submodule_search_locations
    return Path(next(iter(VISMATCH.submodule_search_locations))) / "third_party"


def load_module(name: str, path: Path, package: str | None = None) -> types.ModuleType:
    """A reference source file as a module of its own (its package's __init__ not run)."""
    if package and package not in sys.modules:
        stub = types.ModuleType(package)
        stub.__path__ = [str(path.parent)]
        sys.modules[package] = stub
    full = f"{package}.{name}" if package else name
    spec = importlib.util.spec_from_file_location(full, path)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[full] = module
    spec.loader.exec_module(module)
    return module


def magic_leap(name: str) -> types.ModuleType:
    """Magic Leap's ``models/superpoint.py`` or ``models/superglue.py`` (the release's code)."""
    found = sorted(third_party().glob(f"**/SuperGluePretrainedNetwork/models/{name}.py"))
    if not found:
        pytest.skip(f"Magic Leap's {name}.py is not in {third_party()}; run: {ENABLE}")
    return load_module(f"magic_leap_{name}", found[0])


def scaled_random_state(layout: dict[str, list[int]], seed: int) -> dict[str, torch.Tensor]:
    """Random tensors in an official layout, scaled so activations stay finite and varied
    (He-scaled weights, small biases, BatchNorm near identity): with unscaled weights every
    softmax saturates, and ties would decide what the comparison shows."""
    generator = torch.Generator().manual_seed(seed)
    state: dict[str, torch.Tensor] = {}
    for name, shape in layout.items():
        if name.endswith("num_batches_tracked"):
            state[name] = torch.tensor(7, dtype=torch.long)
        elif name.endswith("running_var"):
            state[name] = torch.rand(shape, generator=generator) + 0.5
        elif name.endswith("running_mean") or name.endswith("bias"):
            state[name] = 0.1 * torch.randn(shape, generator=generator)
        elif len(shape) <= 1:  # BatchNorm weights, SuperGlue's bin score
            state[name] = 1 + 0.1 * torch.randn(shape, generator=generator) if shape else torch.tensor(1.0)
        else:
            fan_in = math.prod(shape[1:])
            state[name] = torch.randn(shape, generator=generator) * math.sqrt(2.0 / fan_in)
    return state


def build_reference(module: types.ModuleType, cls: str, config: dict, state: dict) -> torch.nn.Module:
    """The release's class, whose constructor loads ``weights/*.pth`` with torch.load: it gets
    ``state`` instead (the release's files are not shipped here)."""
    real_load = torch.load
    try:
        torch.load = lambda *args, **kwargs: state  # type: ignore[assignment]
        model = getattr(module, cls)(config)
    finally:
        torch.load = real_load  # type: ignore[assignment]
    return model.eval()


def gardens_point(shared_data: Path, *names: str) -> list[Path]:
    return [shared_data / "gardens_point" / name for name in names]


SUPERPOINT_MAX = methods.resolve_method("sp-sg", "paper")["extractor"]


@pytest.fixture(scope="module")
def superpoint_pair(shared_data, reference_dir):
    """Ours and Magic Leap's SuperPoint with the same random weights, run on two real Gardens
    Point frames prepared as the paper's ``superpoint_max`` conf prepares them (1600 px)."""
    import json

    from gvbench_nb.protocol.features import superpoint as ours_module

    layout = json.loads((reference_dir / "layouts" / "superpoint_v1.layout.json").read_text())
    state = scaled_random_state(layout, seed=1)
    config = {k: SUPERPOINT_MAX[k] for k in ("nms_radius", "keypoint_threshold", "max_keypoints", "remove_borders")}
    ours = ours_module.SuperPoint(config).eval()
    ours.load_state_dict(state, strict=True)
    theirs = build_reference(magic_leap("superpoint"), "SuperPoint", config, state)
    outputs = []
    for path in gardens_point(shared_data, "night_right/Image010.jpg", "day_right/Image011.jpg"):
        image, _ = images.load_for_extraction(path, SUPERPOINT_MAX)
        tensor = torch.from_numpy(image / np.float32(255.0))[None, None]
        with torch.inference_mode(), release_descriptor_sampling():
            outputs.append((tensor.shape, ours(tensor), theirs({"image": tensor})))
    return outputs


@contextlib.contextmanager
def release_descriptor_sampling():
    """vismatch vendors Magic Leap's models/ at revision 826333b, whose guard
    ``int(torch.__version__[2]) > 2`` reads torch 2.14's minor digit and drops
    ``align_corners=True``; the release hloc pins (ddcf11f) tests ``torch.__version__ >= '1.3'``
    and passes it. Its grid_sample call runs here as the pinned release makes it."""
    real = torch.nn.functional.grid_sample
    torch.nn.functional.grid_sample = functools.partial(real, align_corners=True)  # type: ignore[assignment]
    try:
        yield
    finally:
        torch.nn.functional.grid_sample = real  # type: ignore[assignment]


def test_superpoint_equals_magic_leaps_on_real_images(superpoint_pair):
    for _, ours, theirs in superpoint_pair:
        keypoints, scores, descriptors = ours["keypoints"][0], ours["scores"][0], ours["descriptors"][0]
        assert len(keypoints) == SUPERPOINT_MAX["max_keypoints"]  # the 4096 cap is reached
        torch.testing.assert_close(keypoints, theirs["keypoints"][0], rtol=0, atol=0)
        torch.testing.assert_close(scores, theirs["scores"][0], rtol=1e-5, atol=1e-7)
        torch.testing.assert_close(descriptors, theirs["descriptors"][0].t(), rtol=1e-4, atol=1e-5)


def test_superglue_equals_magic_leaps_on_superpoint_features(superpoint_pair, reference_dir):
    """The paper's SuperGlue conf (outdoor layout, 50 Sinkhorn iterations, threshold 0.2) on the
    SuperPoint features above, the first 512 keypoints of each image (the full 4096 x 4096
    problem takes minutes on a 2-core CPU; the computation is the same)."""
    import json

    from gvbench_nb.protocol.matching import superglue as ours_module

    layout = json.loads((reference_dir / "layouts" / "superglue_outdoor.layout.json").read_text())
    state = scaled_random_state(layout, seed=2)
    # He scaling alone lets 18 residual layers swamp the descriptors and leaves every confidence
    # below the 0.2 threshold: damp each layer's update and the keypoint encoding, and sharpen
    # the final projection, so that the comparison covers kept matches too.
    for name in state:
        if name.endswith("mlp.3.weight") or name == "kenc.encoder.12.weight":
            state[name] = state[name] * 0.1
    state["final_proj.weight"] = state["final_proj.weight"] * 16
    conf = methods.resolve_method("sp-sg", "paper")["matcher"]
    config = {"weights": "outdoor", "sinkhorn_iterations": conf["sinkhorn_iterations"]}
    config["match_threshold"] = conf["match_threshold"]
    assert (config["sinkhorn_iterations"], config["match_threshold"]) == (50, 0.2)
    ours = ours_module.SuperGlue(config).eval()
    ours.load_state_dict(state, strict=True)
    theirs = build_reference(magic_leap("superglue"), "SuperGlue", config, state)
    count = 512
    (shape0, side0, _), (shape1, side1, _) = superpoint_pair
    data = {
        "keypoints0": side0["keypoints"][0][None, :count],
        "keypoints1": side1["keypoints"][0][None, :count],
        "scores0": side0["scores"][0][None, :count],
        "scores1": side1["scores"][0][None, :count],
    }
    with torch.inference_mode():
        mine = ours(
            {
                **data,
                "descriptors0": side0["descriptors"][0][None, :count],
                "descriptors1": side1["descriptors"][0][None, :count],
                "image_size0": tuple(shape0[-2:]),
                "image_size1": tuple(shape1[-2:]),
            }
        )
        reference = theirs(
            {
                **data,
                "descriptors0": side0["descriptors"][0][None, :count].transpose(1, 2),
                "descriptors1": side1["descriptors"][0][None, :count].transpose(1, 2),
                "image0": torch.empty(shape0),
                "image1": torch.empty(shape1),
            }
        )
    # Random weights leave the assignment flat, so a row's two best columns can be within float
    # noise of each other and the mutual check flip on it: allow that on at most 1 % of the
    # keypoints, and require equal scores and matches everywhere else.
    for side in "01":
        mine_scores, their_scores = mine[f"matching_scores{side}"], reference[f"matching_scores{side}"]
        both = (mine_scores > 0) == (their_scores > 0)
        assert int((~both).sum()) <= 0.01 * count
        # 18 attention layers and 50 Sinkhorn iterations in float32 accumulate rounding: 1e-3.
        torch.testing.assert_close(mine_scores[both], their_scores[both], rtol=1e-3, atol=2e-4)
        clear = both & ((their_scores - 0.2).abs() > 1e-3)
        assert torch.equal(mine[f"matches{side}"][clear], reference[f"matches{side}"][clear])
    # The comparison sees mutual pairs (scores compared) and kept matches (above 0.2).
    assert int((reference["matching_scores0"] > 0).sum()) >= 20
    assert int((reference["matches0"] > -1).sum()) >= 5


# ----------------------------------------------------------------- LightGlue (DISK) --
def cvg_lightglue() -> type:
    """cvg's LightGlue class from vismatch's copy (its package __init__ imports extractors
    this test does not need)."""
    folder = third_party() / "LightGlue" / "lightglue"
    if not (folder / "lightglue.py").is_file():
        pytest.skip(f"cvg's LightGlue is not in {folder}; run: {ENABLE}")
    module = sys.modules.get("lightglue.lightglue") or load_module("lightglue", folder / "lightglue.py", "lightglue")
    return module.LightGlue


@pytest.fixture(scope="module")
def disk_features(shared_data):
    """DISK features of a real pair as the paper profile stores them (original pixels, float16)."""
    from gvbench_nb.protocol import weights
    from gvbench_nb.protocol.features import build_extractor

    if not weights.is_present("disk_depth") or not weights.is_present("lightglue_disk"):
        pytest.skip("DISK / LightGlue weights missing: run `python -m gvbench_nb weights --link`")
    conf = methods.resolve_method("disk-lg", "paper")["extractor"]
    extractor = build_extractor(conf, torch.device("cpu"))
    features = {}
    for path in gardens_point(shared_data, "night_right/Image090.jpg", "day_right/Image091.jpg"):
        image, scale = images.load_for_extraction(path, conf)
        found = extractor(image)
        features[path.stem + path.parent.name] = {
            "keypoints": images.to_original_pixels(found["keypoints"], scale).astype(np.float16).astype(np.float32),
            "descriptors": found["descriptors"].astype(np.float16).astype(np.float32),
            "image_size": (np.array(image.shape[1::-1]) * scale).astype(np.float32),
        }
    return list(features.values())


def cvg_matches(model, features0: dict, features1: dict, with_image_size: bool) -> set[tuple[int, int]]:
    sides = []
    for features in (features0, features1):
        side = {k: torch.from_numpy(features[k])[None] for k in ("keypoints", "descriptors")}
        if with_image_size:
            side["image_size"] = torch.from_numpy(features["image_size"])[None]
        sides.append(side)
    with torch.inference_mode():
        output = model({"image0": sides[0], "image1": sides[1]})
    return {tuple(int(i) for i in row) for row in output["matches"][0]}


def test_lightglue_equals_cvgs_as_hloc_calls_it(disk_features):
    """kornia's LightGlue (ours, the paper's conf: depth 0.95, width 0.99, filter 0.1, CPU, so
    early stopping and point pruning both run) against cvg's on the same DISK features. hloc's
    match_features hands each side the feature file's ``image_size`` (the original size), as
    ours does; both the per-pair call and the per-image prepared path give cvg's matches."""
    from gvbench_nb.protocol.matching import build_matcher

    conf = methods.resolve_method("disk-lg", "paper")["matcher"]
    options = {k: conf[k] for k in ("depth_confidence", "width_confidence", "filter_threshold")}
    cvg = cvg_lightglue()("disk", **options).eval()
    ours = build_matcher(conf, torch.device("cpu"))
    query, reference = disk_features
    expected = cvg_matches(cvg, query, reference, True)
    assert len(expected) >= 8
    for matches, _ in (ours(query, reference), ours.match_prepared(ours.prepare(query), ours.prepare(reference))):
        assert {tuple(int(i) for i in row) for row in matches} == expected


# ------------------------------------------------------- OpenCV matchers (repository) --
@pytest.mark.parametrize("method", ["orb-nn", "sift-nn"])
def test_repository_opencv_matchers_equal_image_matching_models(shared_data, method):
    """Our repository-profile extractor + matcher against image-matching-models' own matcher
    (``get_matcher(method)._forward``) on the 512x288 images its loader makes: the same matched
    keypoints, in the same order, on real Gardens Point pairs."""
    from vismatch import get_matcher
    from vismatch.utils import _load_image

    from gvbench_nb.protocol.features import build_extractor
    from gvbench_nb.protocol.matching import build_matcher

    conf = methods.resolve_method(method, "repository")
    extractor = build_extractor(conf["extractor"], torch.device("cpu"))
    matcher = build_matcher(conf["matcher"], torch.device("cpu"))
    reference = get_matcher(method, device="cpu", max_num_keypoints=2048)
    pairs = [
        ("night_right/Image010.jpg", "day_right/Image011.jpg"),
        ("night_right/Image050.jpg", "day_right/Image110.jpg"),
        ("night_right/Image130.jpg", "day_right/Image131.jpg"),
    ]
    for names in pairs:
        paths = gardens_point(shared_data, *names)
        features = [extractor(images.load_for_extraction(path, conf["extractor"])[0]) for path in paths]
        matches, _ = matcher(*features)
        theirs = reference._forward(*(_load_image(path, (288, 512)) for path in paths))
        np.testing.assert_array_equal(features[0]["keypoints"], np.asarray(theirs[2], np.float32))
        np.testing.assert_array_equal(features[0]["keypoints"][matches[:, 0]], theirs[0])
        np.testing.assert_array_equal(features[1]["keypoints"][matches[:, 1]], theirs[1])
