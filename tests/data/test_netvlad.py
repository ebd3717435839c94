"""NetVLAD: layout, normalisations and .mat mapping on random weights (no real checkpoint)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import scipy.io
import torch

from gvbench_nb.data import netvlad as nv
from gvbench_nb.protocol import weights

VGG_SHAPES = {
    "conv1_1": (64, 3), "conv1_2": (64, 64),
    "conv2_1": (128, 64), "conv2_2": (128, 128),
    "conv3_1": (256, 128), "conv3_2": (256, 256), "conv3_3": (256, 256),
    "conv4_1": (512, 256), "conv4_2": (512, 512), "conv4_3": (512, 512),
    "conv5_1": (512, 512), "conv5_2": (512, 512), "conv5_3": (512, 512),
}  # fmt: skip


def test_state_dict_layout_is_vgg16_netvlad_wpca() -> None:
    with torch.device("meta"):
        model = nv.NetVLAD()
    expected = {
        f"backbone.{n}.{p}": (o, i, 3, 3) if p == "weight" else (o,)
        for n, (o, i) in VGG_SHAPES.items()
        for p in ("weight", "bias")
    }
    expected |= {
        "vlad.assignment.weight": (64, 512, 1, 1),
        "vlad.centres": (64, 512),
        "whiten.weight": (4096, 32768),
        "whiten.bias": (4096,),
    }
    assert {k: tuple(v.shape) for k, v in model.state_dict().items()} == expected
    assert len(expected) == 30 and model.output_dim == 4096


def unit_features(batch: int, dim: int, h: int, w: int, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return nv.l2_normalise(torch.randn(batch, dim, h, w, generator=g), dim=1)


def test_vlad_layer_matches_a_direct_loop_then_l2_normalises_d_major() -> None:
    torch.manual_seed(1)
    layer = nv.NetVLADLayer(num_clusters=3, dim=4)
    features = unit_features(2, 4, 2, 3, seed=2)
    x = features[0].flatten(1)  # (D, N)
    soft = torch.softmax(layer.assignment.weight[:, :, 0, 0] @ x, dim=0)  # (K, N)
    expected = torch.zeros(4, 3)
    for k in range(3):
        for n in range(x.shape[1]):
            expected[:, k] += soft[k, n] * (x[:, n] - layer.centres[k])
    expected = expected / expected.norm(dim=0, keepdim=True)  # intra-normalised: each cluster unit norm
    blocks = layer.aggregate(features)  # (B, D, K) before the final L2
    torch.testing.assert_close(blocks[0], expected.detach(), rtol=1e-5, atol=1e-6)
    out = layer(features)
    assert out.shape == (2, 12)
    torch.testing.assert_close(out.norm(dim=1), torch.ones(2))
    # d-major flattening: out[d * K + k] is cluster k's component d, scaled by 1/sqrt(K)
    torch.testing.assert_close(out.view(2, 4, 3), blocks / 3**0.5)


def test_preprocessing_caps_longest_side_and_model_gives_unit_4096_descriptor() -> None:
    assert nv.image_to_tensor(np.zeros((1500, 2048, 3), np.uint8)).shape == (1, 3, 750, 1024)
    assert nv.image_to_tensor(np.zeros((300, 400, 3), np.uint8)).shape == (1, 3, 300, 400)  # never enlarged
    torch.manual_seed(0)
    image = nv.image_to_tensor(np.random.default_rng(0).integers(0, 256, (40, 56, 3), dtype=np.uint8))
    with torch.inference_mode():
        out = nv.NetVLAD().eval()(image)
    assert out.shape == (1, 4096)
    torch.testing.assert_close(out.norm(dim=1), torch.ones(1))


def fake_mat(path: Path, whitened_dim: int, rng: np.random.Generator) -> dict[str, np.ndarray]:
    """A Pitts30K_struct.mat look-alike (MATLAB layouts, small WPCA) and its arrays."""
    layers, arrays = [], {}
    for block, count, _ in nv.VGG16_BLOCKS:
        for i in range(1, count + 1):
            name = f"conv{block}_{i}"
            out_c, in_c = VGG_SHAPES[name]
            kernel = rng.standard_normal((3, 3, in_c, out_c), dtype=np.float32) * 0.05
            bias = rng.standard_normal(out_c, dtype=np.float32) * 0.01
            arrays[name] = kernel
            layers.append({"name": name, "type": "conv", "weights": np.array([kernel, bias], dtype=object)})
            if name != "conv5_3":
                layers.append({"name": f"relu{block}_{i}", "type": "relu"})
        if block < 5:
            layers.append({"name": f"pool{block}", "type": "pool"})
    layers.append({"name": "preL2", "type": "normalize"})
    assignment = rng.standard_normal((512, 64), dtype=np.float32)
    centres = rng.standard_normal((512, 64), dtype=np.float32)
    arrays["assignment"], arrays["centres"] = assignment, centres
    layers.append({"name": "vlad:core", "type": "custom", "weights": np.array([assignment, -centres], dtype=object)})
    layers += [{"name": "vlad:intranorm", "type": "normalize"}, {"name": "postL2", "type": "custom"}]
    projection = rng.standard_normal((1, 1, 32768, whitened_dim), dtype=np.float32)
    arrays["projection"] = projection
    wpca_weights = np.array([projection, np.zeros((whitened_dim, 1), np.float32)], dtype=object)
    layers += [{"name": "WPCA", "type": "conv", "weights": wpca_weights}, {"name": "finalL2", "type": "custom"}]
    cell = np.empty(len(layers), dtype=object)
    cell[:] = layers
    average = np.tile(np.array([122.0, 117.0, 104.0], np.float32), (224, 224, 1))
    scipy.io.savemat(path, {"net": {"layers": cell, "meta": {"normalization": {"averageImage": average}}}})
    return arrays


def test_load_netvlad_maps_mat_layers(empty_hub: Path) -> None:
    empty_hub.mkdir(parents=True)
    arrays = fake_mat(empty_hub / "Pitts30K_struct.mat", whitened_dim=8, rng=np.random.default_rng(0))
    model = nv.load_netvlad()  # from where `weights fetch` puts it
    state = model.state_dict()
    # MATLAB (h, w, in, out) -> torch (out, in, h, w)
    np.testing.assert_array_equal(state["backbone.conv2_1.weight"][5, 7].numpy(), arrays["conv2_1"][:, :, 7, 5])
    np.testing.assert_array_equal(state["vlad.assignment.weight"][3, :, 0, 0].numpy(), arrays["assignment"][:, 3])
    np.testing.assert_array_equal(state["vlad.centres"][3].numpy(), arrays["centres"][:, 3])  # un-negated
    np.testing.assert_array_equal(state["whiten.weight"][2].numpy(), arrays["projection"][0, 0, :, 2])
    torch.testing.assert_close(model.average_rgb, torch.tensor([122.0, 117.0, 104.0]))
    assert model.output_dim == 8


def test_missing_mat_names_file_and_url(empty_hub: Path) -> None:
    with pytest.raises(weights.MissingWeightsError) as error:
        nv.load_netvlad()
    assert "https://cvg-data.inf.ethz.ch/hloc/netvlad/Pitts30K_struct.mat" in str(error.value)
    assert str(empty_hub) in str(error.value)
