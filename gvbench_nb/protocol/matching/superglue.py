"""SuperGlue (Sarlin et al., CVPR 2020) whose ``state_dict`` matches Magic Leap's
``superglue_outdoor.pth`` (strict load); channel-first (B, D, N) inside as in the release, (B, N, D)
outside. Weights: Magic Leap, non-commercial research only."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from copy import deepcopy
from typing import Any, cast

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor, nn

from gvbench_nb.protocol import registry, weights
from gvbench_nb.protocol.matching.base import Matcher, Matches, empty_matches

CHECKPOINTS = {"outdoor": "superglue_outdoor"}


def mlp(channels: Sequence[int]) -> nn.Sequential:
    """1x1 Conv1d layers with BatchNorm + ReLU between them; the Sequential indices are the
    checkpoint's tensor names, so the layer order matters."""
    layers: list[nn.Module] = []
    for i in range(1, len(channels)):
        layers.append(nn.Conv1d(channels[i - 1], channels[i], kernel_size=1, bias=True))
        if i < len(channels) - 1:
            layers += [nn.BatchNorm1d(channels[i]), nn.ReLU()]
    return nn.Sequential(*layers)


def normalize_keypoints(kpts: Tensor, image_size: tuple[int, int]) -> Tensor:
    """Centre (B, N, 2) keypoints on the image of ``image_size`` (H, W) and scale by 0.7 * the
    longest side."""
    height, width = image_size
    size = kpts.new_tensor([width, height])
    return (kpts - size / 2) / (size.max() * 0.7)


class KeypointEncoder(nn.Module):
    """Embeds (x, y, score) into the descriptor space with an MLP."""

    def __init__(self, feature_dim: int, layers: Sequence[int]) -> None:
        super().__init__()
        self.encoder = mlp([3, *layers, feature_dim])
        # The last layer is a Conv1d with a bias; Module.__getattr__ types it Tensor | Module.
        nn.init.constant_(cast(Tensor, self.encoder[-1].bias), 0.0)

    def forward(self, kpts: Tensor, scores: Tensor) -> Tensor:
        """``kpts`` (B, N, 2) normalised, ``scores`` (B, N) -> (B, D, N)."""
        inputs = torch.cat([kpts.transpose(1, 2), scores.unsqueeze(1)], dim=1)
        return self.encoder(inputs)


class MultiHeadedAttention(nn.Module):
    """Multi-head attention with the release's channel split: channel ``c`` is head ``c % num_heads``
    (head index fastest); the usual split would silently scramble the official weights' heads."""

    def __init__(self, num_heads: int, d_model: int) -> None:
        super().__init__()
        if d_model % num_heads != 0:
            raise ValueError(f"d_model {d_model} is not divisible by num_heads {num_heads}")
        self.dim = d_model // num_heads
        self.num_heads = num_heads
        # ``merge`` is created first: the checkpoint lists it before ``proj``.
        self.merge = nn.Conv1d(d_model, d_model, kernel_size=1)
        self.proj = nn.ModuleList([deepcopy(self.merge) for _ in range(3)])

    def forward(self, query: Tensor, key: Tensor, value: Tensor) -> Tensor:
        # (B, dim*heads, N) -> (B, heads, N, dim), head index fastest in the channels.
        b, _, n = query.shape
        q, k, v = (
            layer(x).unflatten(1, (self.dim, self.num_heads)).permute(0, 2, 3, 1)
            for layer, x in zip(self.proj, (query, key, value))
        )
        # softmax(q k^T / sqrt(dim)) v; the fused kernel saves memory on long sets.
        out = F.scaled_dot_product_attention(q, k, v)
        return self.merge(out.permute(0, 3, 1, 2).reshape(b, self.dim * self.num_heads, n))


class AttentionalPropagation(nn.Module):
    """One GNN layer: message = MLP([x, attention(x, source)]), returned as the update."""

    def __init__(self, feature_dim: int, num_heads: int) -> None:
        super().__init__()
        self.attn = MultiHeadedAttention(num_heads, feature_dim)
        self.mlp = mlp([feature_dim * 2, feature_dim * 2, feature_dim])
        # The last layer is a Conv1d with a bias; Module.__getattr__ types it Tensor | Module.
        nn.init.constant_(cast(Tensor, self.mlp[-1].bias), 0.0)

    def forward(self, x: Tensor, source: Tensor) -> Tensor:
        message = self.attn(x, source, source)
        return self.mlp(torch.cat([x, message], dim=1))


class AttentionalGNN(nn.Module):
    """Stack of layers; 'self' attends within an image, 'cross' to the other image."""

    def __init__(self, feature_dim: int, layer_names: Sequence[str]) -> None:
        super().__init__()
        for name in layer_names:
            if name not in ("self", "cross"):
                raise ValueError(f"GNN layer must be 'self' or 'cross', got {name!r}")
        self.layers = nn.ModuleList([AttentionalPropagation(feature_dim, 4) for _ in layer_names])
        self.names = list(layer_names)

    def forward(self, desc0: Tensor, desc1: Tensor) -> tuple[Tensor, Tensor]:
        for layer, name in zip(self.layers, self.names):
            src0, src1 = (desc1, desc0) if name == "cross" else (desc0, desc1)
            # Both updates are computed from the previous state before either is applied.
            delta0, delta1 = layer(desc0, src0), layer(desc1, src1)
            desc0, desc1 = desc0 + delta0, desc1 + delta1
        return desc0, desc1


def log_sinkhorn_iterations(z: Tensor, log_mu: Tensor, log_nu: Tensor, iters: int) -> Tensor:
    """Sinkhorn normalisation in log space: returns log P with P's row sums ~ mu and
    column sums ~ nu. ``z``: (B, M, N), ``log_mu``: (B, M), ``log_nu``: (B, N)."""
    u, v = torch.zeros_like(log_mu), torch.zeros_like(log_nu)
    for _ in range(iters):
        u = log_mu - torch.logsumexp(z + v.unsqueeze(1), dim=2)
        v = log_nu - torch.logsumexp(z + u.unsqueeze(2), dim=1)
    return z + u.unsqueeze(2) + v.unsqueeze(1)


def log_optimal_transport(scores: Tensor, alpha: Tensor, iters: int) -> Tensor:
    """Log-space optimal transport with dustbins: (B, M, N) scores -> (B, M+1, N+1) log-assignment;
    rows and columns carry mass 1, the dustbin row N and the dustbin column M, as in the release."""
    b, m, n = scores.shape
    ms = scores.new_tensor(float(m))
    ns = scores.new_tensor(float(n))

    bins0 = alpha.expand(b, m, 1)
    bins1 = alpha.expand(b, 1, n)
    corner = alpha.expand(b, 1, 1)
    couplings = torch.cat([torch.cat([scores, bins0], -1), torch.cat([bins1, corner], -1)], 1)

    # Solve for probabilities summing to 1 (numerically tamer), rescale at the end.
    norm = -(ms + ns).log()
    log_mu = torch.cat([norm.expand(m), ns.log()[None] + norm])
    log_nu = torch.cat([norm.expand(n), ms.log()[None] + norm])
    log_mu, log_nu = log_mu[None].expand(b, -1), log_nu[None].expand(b, -1)

    z = log_sinkhorn_iterations(couplings, log_mu, log_nu, iters)
    return z - norm  # multiply the probabilities by M+N


class SuperGlue(nn.Module):
    """SuperGlue with the official checkpoint's layout. ``forward`` takes ``keypoints0/1`` (B, N, 2),
    ``scores0/1``, ``descriptors0/1`` (B, N, D) and ``image_size0/1`` (H, W), and
    returns mutual ``matches0/1`` (-1 unmatched, also below ``match_threshold``) and
    ``matching_scores0/1``, as in the release. Call ``eval()`` first (``load_superglue`` does)."""

    default_conf: dict[str, Any] = {
        "descriptor_dim": 256,
        "weights": "outdoor",
        "keypoint_encoder": [32, 64, 128, 256],
        "GNN_layers": ["self", "cross"] * 9,
        "sinkhorn_iterations": 100,
        "match_threshold": 0.2,
    }

    def __init__(self, conf: Mapping[str, Any] | None = None) -> None:
        super().__init__()
        self.conf = {**self.default_conf, **(conf or {})}
        dim = self.conf["descriptor_dim"]

        self.kenc = KeypointEncoder(dim, self.conf["keypoint_encoder"])
        self.gnn = AttentionalGNN(dim, self.conf["GNN_layers"])
        self.final_proj = nn.Conv1d(dim, dim, kernel_size=1, bias=True)
        self.bin_score = nn.Parameter(torch.tensor(1.0))

    def forward(self, data: Mapping[str, Any]) -> dict[str, Tensor]:
        kpts0, kpts1 = data["keypoints0"], data["keypoints1"]
        desc0 = data["descriptors0"].transpose(1, 2)  # (B, N, D) -> (B, D, N)
        desc1 = data["descriptors1"].transpose(1, 2)

        if kpts0.shape[1] == 0 or kpts1.shape[1] == 0:  # nothing to match
            shape0, shape1 = kpts0.shape[:-1], kpts1.shape[:-1]
            return {
                "matches0": kpts0.new_full(shape0, -1, dtype=torch.long),
                "matches1": kpts1.new_full(shape1, -1, dtype=torch.long),
                "matching_scores0": kpts0.new_zeros(shape0),
                "matching_scores1": kpts1.new_zeros(shape1),
            }

        # Positional encoding, on normalised coordinates.
        norm0 = normalize_keypoints(kpts0, data["image_size0"])
        norm1 = normalize_keypoints(kpts1, data["image_size1"])
        desc0 = desc0 + self.kenc(norm0, data["scores0"])
        desc1 = desc1 + self.kenc(norm1, data["scores1"])

        desc0, desc1 = self.gnn(desc0, desc1)
        mdesc0, mdesc1 = self.final_proj(desc0), self.final_proj(desc1)

        scores = torch.einsum("bdn,bdm->bnm", mdesc0, mdesc1) / self.conf["descriptor_dim"] ** 0.5
        scores = log_optimal_transport(scores, self.bin_score, self.conf["sinkhorn_iterations"])
        return mutual_matches(scores, self.conf["match_threshold"])


def mutual_matches(log_assignment: Tensor, threshold: float) -> dict[str, Tensor]:
    """Mutual argmax of the (B, M+1, N+1) log-assignment ignoring dustbins, kept above
    ``threshold``; both sides get the same score."""
    inner = log_assignment[:, :-1, :-1]
    max0, max1 = inner.max(2), inner.max(1)
    indices0, indices1 = max0.indices, max1.indices
    arange0 = torch.arange(indices0.shape[1], device=inner.device)[None]
    arange1 = torch.arange(indices1.shape[1], device=inner.device)[None]
    mutual0 = arange0 == indices1.gather(1, indices0)
    mutual1 = arange1 == indices0.gather(1, indices1)
    zero = inner.new_tensor(0)
    mscores0 = torch.where(mutual0, max0.values.exp(), zero)
    mscores1 = torch.where(mutual1, mscores0.gather(1, indices1), zero)
    valid0 = mutual0 & (mscores0 > threshold)
    valid1 = mutual1 & valid0.gather(1, indices1)
    minus_one = indices0.new_tensor(-1)
    return {
        "matches0": torch.where(valid0, indices0, minus_one),
        "matches1": torch.where(valid1, indices1, minus_one),
        "matching_scores0": mscores0,
        "matching_scores1": mscores1,
    }


def load_superglue(conf: Mapping[str, Any] | None = None, device: str | torch.device = "cpu") -> SuperGlue:
    """SuperGlue with the official ``conf['weights']`` ('outdoor'), in eval mode; raises
    ``MissingWeightsError`` or ``WeightsLayoutError`` (see ``weights``)."""
    model = SuperGlue(conf)
    which = model.conf["weights"]
    return weights.load_pretrained(
        model, registry.lookup("SuperGlue weights", which, CHECKPOINTS, error=ValueError), device
    )


class SuperGlueMatcher(Matcher):
    """The SuperGlue above on the official outdoor weights."""

    type = "magicleap_superglue"

    def __init__(self, conf: dict[str, Any], device: torch.device):
        self.device = device
        model_conf: dict[str, Any] = {k: conf[k] for k in ("sinkhorn_iterations", "match_threshold") if k in conf}
        self.model = load_superglue(model_conf, device=device)

    @torch.inference_mode()
    def __call__(self, features0: dict[str, np.ndarray], features1: dict[str, np.ndarray]) -> Matches:
        if len(features0["keypoints"]) == 0 or len(features1["keypoints"]) == 0:
            return empty_matches()
        data: dict[str, Any] = {}
        for i, features in enumerate((features0, features1)):
            for key in ("keypoints", "scores", "descriptors"):
                data[f"{key}{i}"] = torch.from_numpy(features[key]).float()[None].to(self.device)
            width, height = (int(v) for v in features["image_size"])
            data[f"image_size{i}"] = (height, width)
        output = self.model(data)
        matches0 = output["matches0"][0].cpu().numpy()
        scores0 = output["matching_scores0"][0].cpu().numpy()
        valid = matches0 > -1
        matches = np.stack([np.nonzero(valid)[0], matches0[valid]], axis=1).astype(np.int64)
        return matches, scores0[valid].astype(np.float32)
