"""NetVLAD (VGG16 + NetVLAD + whitening, Pitts30K weights, Arandjelovic et al., CVPR 2016) in plain
PyTorch: GV-Bench's retrieval descriptor. MatConvNet's ``Pitts30K_struct.mat`` stores the centres
negated and VLAD d-major (index d * K + k); the average colour is ``averageImage[0, 0]``, as in hloc."""

from __future__ import annotations

import os
from collections.abc import Iterable, Sequence
from typing import Any

import cv2
import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from gvbench_nb.protocol import weights
from gvbench_nb.protocol.images import read_image

CHECKPOINT_NAME = "netvlad_pitts30k"
MAX_SIDE = 1024
NUM_CLUSTERS = 64
FEATURE_DIM = 512
WHITENED_DIM = 4096
# MatConvNet's normalisation adds 1e-12 under the square root; a tiny eps keeps us equal.
NORM_EPS = 1e-12

# (block, number of convs, output channels) of VGG16's conv part.
VGG16_BLOCKS: tuple[tuple[int, int, int], ...] = ((1, 2, 64), (2, 2, 128), (3, 3, 256), (4, 3, 512), (5, 3, 512))
VGG16_CONV_NAMES: tuple[str, ...] = tuple(f"conv{b}_{i}" for b, n, _ in VGG16_BLOCKS for i in range(1, n + 1))


def l2_normalise(x: torch.Tensor, dim: int) -> torch.Tensor:
    """x / sqrt(sum x^2 + eps), MatConvNet's form (not clamped like F.normalize)."""
    return x / torch.sqrt((x * x).sum(dim=dim, keepdim=True) + NORM_EPS)


class VGG16Conv5(nn.Module):
    """VGG16 convolutions up to conv5_3, without the last ReLU and max-pool."""

    def __init__(self) -> None:
        super().__init__()
        channels = [3, *(c for _, count, c in VGG16_BLOCKS for _ in range(count))]
        for name, in_channels, out_channels in zip(VGG16_CONV_NAMES, channels, channels[1:]):
            self.add_module(name, nn.Conv2d(in_channels, out_channels, 3, padding=1))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        for name in VGG16_CONV_NAMES[:-1]:  # NetVLAD crops at conv5_3 before its ReLU
            x = F.relu(getattr(self, name)(x))
            if name in ("conv1_2", "conv2_2", "conv3_3", "conv4_3"):
                x = F.max_pool2d(x, 2, 2)
        return getattr(self, VGG16_CONV_NAMES[-1])(x)


class NetVLADLayer(nn.Module):
    """Soft-assignment VLAD pooling with intra-normalisation and L2: (B, D, h, w) L2-normalised
    features -> (B, D * K), d-major (index d * K + k), unit norm."""

    def __init__(self, num_clusters: int = NUM_CLUSTERS, dim: int = FEATURE_DIM) -> None:
        super().__init__()
        self.assignment = nn.Conv2d(dim, num_clusters, 1, bias=False)
        self.centres = nn.Parameter(torch.empty(num_clusters, dim))
        nn.init.normal_(self.centres, std=dim**-0.5)

    def aggregate(self, features: torch.Tensor) -> torch.Tensor:
        """Intra-normalised VLAD matrix (B, D, K) before the flattening L2."""
        soft = F.softmax(self.assignment(features), dim=1).flatten(2)  # (B, K, N)
        x = features.flatten(2)  # (B, D, N)
        # sum_n a_kn (x_dn - c_kd) = (x a^T)_dk - c_kd * sum_n a_kn
        weighted = torch.einsum("bdn,bkn->bdk", x, soft)
        vlad = weighted - self.centres.t().unsqueeze(0) * soft.sum(dim=2).unsqueeze(1)
        return l2_normalise(vlad, dim=1)  # intra-normalisation: per cluster over D

    def forward(self, features: torch.Tensor) -> torch.Tensor:
        vlad = self.aggregate(features)
        return l2_normalise(vlad.flatten(1), dim=1)


class NetVLAD(nn.Module):
    """VGG16-NetVLAD with whitening: image (B, 3, H, W) RGB 0..255 -> descriptor."""

    average_rgb: torch.Tensor  # a buffer (register_buffer below)

    def __init__(
        self,
        num_clusters: int = NUM_CLUSTERS,
        whitened_dim: int = WHITENED_DIM,
        average_rgb: Sequence[float] = (123.68, 116.779, 103.939),
    ) -> None:
        super().__init__()
        self.backbone = VGG16Conv5()
        self.vlad = NetVLADLayer(num_clusters, FEATURE_DIM)
        self.whiten = nn.Linear(num_clusters * FEATURE_DIM, whitened_dim)
        # A buffer set from the .mat, kept out of the state dict (not a learnt weight).
        self.register_buffer("average_rgb", torch.tensor(average_rgb, dtype=torch.float32), persistent=False)

    @property
    def output_dim(self) -> int:
        return self.whiten.out_features

    def forward(self, image: torch.Tensor) -> torch.Tensor:
        """image: (B, 3, H, W) RGB in 0..255 (mean not yet removed)."""
        x = image - self.average_rgb.view(1, 3, 1, 1)
        features = l2_normalise(self.backbone(x), dim=1)  # preL2, per location
        return l2_normalise(self.whiten(self.vlad(features)), dim=1)


def _mat_field(obj: Any, name: str) -> Any:
    if not hasattr(obj, name):  # a clear message rather than AttributeError
        raise weights.WeightsLayoutError(f"NetVLAD .mat: struct has no field {name!r}")
    return getattr(obj, name)


def _layer(mat_net: Any, *names: str) -> Any:
    layers = {
        str(getattr(layer, "name", f"#{i}")): layer
        for i, layer in enumerate(np.atleast_1d(_mat_field(mat_net, "layers")))
    }
    for name in names:
        if name in layers:
            return layers[name]
    raise weights.WeightsLayoutError(
        f"NetVLAD .mat: no layer named {' or '.join(map(repr, names))}; layers: {', '.join(layers)}"
    )


def _as_tensor(array: Any) -> torch.Tensor:
    return torch.from_numpy(np.ascontiguousarray(np.asarray(array, dtype=np.float32)))


def average_rgb_from_mat(mat_net: Any) -> np.ndarray:
    """The average colour (3,) from ``net.meta.normalization.averageImage``."""
    average = np.asarray(_mat_field(_mat_field(_mat_field(mat_net, "meta"), "normalization"), "averageImage"), float)
    if average.ndim == 3:
        return average[0, 0, :]  # a constant image in the released nets; take pixel [0, 0]
    return average.reshape(3)


def state_dict_from_mat(mat_net: Any) -> dict[str, torch.Tensor]:
    """Our NetVLAD state dict (module docstring) from the loadmat struct ``mat['net']``."""
    state: dict[str, torch.Tensor] = {}
    for name in VGG16_CONV_NAMES:
        kernel, bias = _mat_field(_layer(mat_net, name), "weights")
        state[f"backbone.{name}.weight"] = _as_tensor(kernel).permute(3, 2, 0, 1).contiguous()  # HWIO -> OIHW
        state[f"backbone.{name}.bias"] = _as_tensor(bias).reshape(-1)

    assignment, negated_centres = _mat_field(_layer(mat_net, "vlad:core", "vlad_core"), "weights")
    assignment = _as_tensor(assignment).reshape(FEATURE_DIM, -1)  # D x K
    state["vlad.assignment.weight"] = assignment.t().contiguous()[:, :, None, None]
    state["vlad.centres"] = (-_as_tensor(negated_centres).reshape(FEATURE_DIM, -1)).t().contiguous()

    projection, bias = _mat_field(_layer(mat_net, "WPCA"), "weights")
    projection = _as_tensor(projection)
    state["whiten.weight"] = projection.reshape(projection.shape[-2], projection.shape[-1]).t().contiguous()
    state["whiten.bias"] = _as_tensor(bias).reshape(-1)
    return state


def load_netvlad(device: str | torch.device = "cpu") -> NetVLAD:
    """NetVLAD with the Pitts30K weights (``<torch hub dir>/checkpoints/Pitts30K_struct.mat``, a MATLAB
    file: not one for torch.load), in eval mode."""
    from scipy.io import loadmat  # scipy only needed when loading real weights

    path = weights.checkpoint_path(CHECKPOINT_NAME)
    if not path.is_file():
        raise weights.MissingWeightsError(f"{path} not found\n" + weights.missing_message(CHECKPOINT_NAME))
    mat_net = loadmat(str(path), struct_as_record=False, squeeze_me=True)["net"]
    state = state_dict_from_mat(mat_net)
    model = NetVLAD(
        num_clusters=state["vlad.centres"].shape[0],
        whitened_dim=state["whiten.weight"].shape[0],
        average_rgb=tuple(float(v) for v in average_rgb_from_mat(mat_net)),
    )
    weights.load_state_dict_strict(model, state, str(path))
    return model.eval().to(device)


def image_to_tensor(image_rgb: np.ndarray, max_side: int = MAX_SIDE) -> torch.Tensor:
    """(H, W, 3) uint8 RGB -> (1, 3, h, w) float 0..255, shrunk (never enlarged, INTER_AREA
    as hloc) so the longest side is <= max_side."""
    if image_rgb.ndim != 3 or image_rgb.shape[2] != 3:
        raise ValueError(f"expected an (H, W, 3) RGB image, got shape {image_rgb.shape}")
    height, width = image_rgb.shape[:2]
    scale = max_side / max(height, width)
    if scale < 1.0:
        size = (max(1, round(width * scale)), max(1, round(height * scale)))
        image_rgb = cv2.resize(image_rgb, size, interpolation=cv2.INTER_AREA)
    image = image_rgb.astype(np.float32)
    return torch.from_numpy(image).permute(2, 0, 1).unsqueeze(0).contiguous()


@torch.inference_mode()
def describe_images(model: NetVLAD, image_paths: Iterable[str | os.PathLike[str]]) -> np.ndarray:
    """NetVLAD descriptors (N, output_dim) float32, one image at a time (sizes differ)."""
    device = next(model.parameters()).device
    rows = [
        model(image_to_tensor(read_image(p, exif_orientation=True)).to(device))[0].cpu().numpy() for p in image_paths
    ]
    return np.stack(rows).astype(np.float32) if rows else np.zeros((0, model.output_dim), np.float32)
