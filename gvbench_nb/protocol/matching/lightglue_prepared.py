"""kornia's LightGlue forward split so one-image work (input projection, positional encoding,
layer-0 self-attention, cross projections) runs once per image (``prepare_image``); ``match_prepared``
runs the rest with kornia 0.9's modules in ``LightGlue.forward``'s order, bit-identical
(tests/protocol/test_lightglue_prepared.py); only the paper's configuration (``supports_prepared``)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import cast

import torch
import torch.nn.functional as F
from kornia.feature.lightglue import (
    CrossBlock,
    LightGlue,
    MatchAssignment,
    TransformerLayer,
    filter_matches,
    normalize_keypoints,
)

try:  # kornia 0.9 checks the normalised range in LightGlue.forward; 0.8 (the opt-in venv's) does not
    from kornia.feature.lightglue import _check_keypoints_normalized
except ImportError:

    def _check_keypoints_normalized(keypoints: torch.Tensor) -> None:  # type: ignore[misc]
        """What kornia 0.9 checks: keypoints normalised by their image size lie in [-1, 1]."""
        if not (torch.all(keypoints >= -1) and torch.all(keypoints <= 1)):
            raise ValueError("keypoints normalised by the image size must lie in [-1, 1]; check image_size")


@dataclass(frozen=True)
class PreparedImage:
    """One image's LightGlue state up to its first meeting with another image."""

    descriptors: torch.Tensor  # (1, N, D): after the layer-0 self-attention block
    encoding: torch.Tensor  # (2, 1, 1, N, head_dim): rotary positional encoding
    query_key: torch.Tensor  # (1, H, N, head_dim): layer-0 cross block, scaled as kornia scales it
    value: torch.Tensor  # (1, H, N, head_dim): layer-0 cross block

    @property
    def num_keypoints(self) -> int:
        return int(self.descriptors.shape[1])

    def nbytes(self) -> int:
        return sum(t.numel() * t.element_size() for t in (self.descriptors, self.encoding, self.query_key, self.value))


def supports_prepared(model: LightGlue) -> bool:
    """Whether ``model`` runs the plain single-pair path that this module reproduces."""
    conf = model.conf
    return not (conf.mp or conf.add_scale_ori or conf.add_laf or model.static_lengths)


@torch.inference_mode()
def prepare_image(
    model: LightGlue, keypoints: torch.Tensor, descriptors: torch.Tensor, image_size: torch.Tensor
) -> PreparedImage:
    """The per-image part of LightGlue for ``keypoints`` (1, N, 2) in pixels,
    ``descriptors`` (1, N, input_dim) and ``image_size`` (1, 2) as (width, height); N > 0."""
    keypoints = normalize_keypoints(keypoints, image_size).clone()
    _check_keypoints_normalized(keypoints)
    descriptors = model.input_proj(descriptors.detach().contiguous())
    encoding = model.posenc(keypoints.to(model.posenc.Wr.weight.dtype))
    layer = _transformer(model, 0)
    descriptors = layer.self_attn(descriptors, encoding)
    query_key, value = _projections(layer.cross_attn, descriptors)
    return PreparedImage(descriptors, encoding, query_key, value)


CROSS_ATTENTIONS = ("kornia", "sdpa")


def _transformer(model: LightGlue, index: int) -> TransformerLayer:
    # kornia fills model.transformers with TransformerLayers; ModuleList types its items Module.
    return cast(TransformerLayer, model.transformers[index])


def _cross_messages(
    query_key0: torch.Tensor, query_key1: torch.Tensor, value0: torch.Tensor, value1: torch.Tensor, attention: str
) -> tuple[torch.Tensor, torch.Tensor]:
    """Bidirectional cross-attention of pre-scaled (1, H, N, d) query/keys: ``kornia`` softmaxes one
    similarity both ways; ``sdpa`` calls torch's fused kernel per direction (scale 1), equal to rounding."""
    if attention == "sdpa":
        message0 = F.scaled_dot_product_attention(query_key0, query_key1, value1, scale=1.0)
        message1 = F.scaled_dot_product_attention(query_key1, query_key0, value0, scale=1.0)
        return message0, message1
    sim = torch.einsum("bhid, bhjd -> bhij", query_key0, query_key1)
    attn01 = F.softmax(sim, dim=-1)
    attn10 = F.softmax(sim.transpose(-2, -1).contiguous(), dim=-1)
    message0 = torch.einsum("bhij, bhjd -> bhid", attn01, value1)
    message1 = torch.einsum("bhji, bhjd -> bhid", attn10.transpose(-2, -1), value0)
    return message0, message1


def _cross_block(
    cross: CrossBlock,
    x0: torch.Tensor,
    x1: torch.Tensor,
    query_key0: torch.Tensor,
    query_key1: torch.Tensor,
    value0: torch.Tensor,
    value1: torch.Tensor,
    attention: str,
) -> tuple[torch.Tensor, torch.Tensor]:
    """The rest of kornia's ``CrossBlock.forward`` (CPU path, no mask) from its projections."""
    message0, message1 = _cross_messages(query_key0, query_key1, value0, value1, attention)
    message0, message1 = (cross.to_out(t.transpose(1, 2).flatten(start_dim=-2)) for t in (message0, message1))
    return x0 + cross.ffn(torch.cat([x0, message0], -1)), x1 + cross.ffn(torch.cat([x1, message1], -1))


def _projections(cross: CrossBlock, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """A cross block's query/key (scaled as kornia's CPU path scales it) and value, by head."""
    query_key, value = cross.to_qk(x), cross.to_v(x)
    query_key, value = (t.unflatten(-1, (cross.heads, -1)).transpose(1, 2) for t in (query_key, value))
    return query_key * cross.scale**0.5, value


def _layer(
    model: LightGlue,
    index: int,
    desc0: torch.Tensor,
    desc1: torch.Tensor,
    encoding0: torch.Tensor,
    encoding1: torch.Tensor,
    attention: str,
) -> tuple[torch.Tensor, torch.Tensor]:
    """kornia ``TransformerLayer.forward`` (no masks); kornia's own module when attention is kornia's."""
    layer = _transformer(model, index)
    if attention == "kornia":
        return layer(desc0, desc1, encoding0, encoding1)
    desc0, desc1 = layer.self_attn(desc0, encoding0), layer.self_attn(desc1, encoding1)
    (query_key0, value0), (query_key1, value1) = (_projections(layer.cross_attn, d) for d in (desc0, desc1))
    return _cross_block(layer.cross_attn, desc0, desc1, query_key0, query_key1, value0, value1, attention)


def _prune(
    model: LightGlue,
    layer: int,
    confidence: torch.Tensor | None,
    descriptors: torch.Tensor,
    encoding: torch.Tensor,
    indices: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """One image's point pruning after ``layer``: the points LightGlue keeps, as kornia keeps them."""
    # kornia fills model.log_assignment with MatchAssignments; ModuleList types its items Module.
    matchability = cast(MatchAssignment, model.log_assignment[layer]).get_matchability(descriptors)
    # kornia hints confidences as a Tensor but takes None (no early stopping): prune on matchability alone.
    keep = torch.where(model.get_pruning_mask(confidence, matchability, layer))[1]  # type: ignore[arg-type]
    return descriptors.index_select(1, keep), encoding.index_select(-2, keep), indices.index_select(1, keep)


@torch.inference_mode()
def match_prepared(
    model: LightGlue, image0: PreparedImage, image1: PreparedImage, cross_attention: str = "kornia"
) -> tuple[torch.Tensor, torch.Tensor]:
    """Matches (K, 2) and scores (K,) of one pair from its prepared images, as kornia's ``model(...)``
    with ``cross_attention="kornia"``; ``"sdpa"`` (``_cross_messages``) can change a near-threshold match."""
    if image0.descriptors.device.type == "cuda" and _transformer(model, 0).cross_attn.flash is not None:
        raise ValueError(
            "match_prepared reproduces LightGlue's CPU cross-attention only; use LightGlue.forward on CUDA"
        )
    m, n = image0.num_keypoints, image1.num_keypoints
    device = image0.descriptors.device
    conf = model.conf
    do_early_stop = conf.depth_confidence > 0
    do_point_pruning = conf.width_confidence > 0
    pruning_th = model.pruning_min_kpts(device)
    ind0 = torch.arange(0, m, device=device)[None]
    ind1 = torch.arange(0, n, device=device)[None]
    encoding0, encoding1 = image0.encoding, image1.encoding
    desc0 = desc1 = None
    for i in range(conf.n_layers):
        if i == 0:  # kornia's CrossBlock.forward of layer 0, from the prepared projections
            desc0, desc1 = _cross_block(
                _transformer(model, 0).cross_attn,
                image0.descriptors,
                image1.descriptors,
                image0.query_key,
                image1.query_key,
                image0.value,
                image1.value,
                cross_attention,
            )
        else:
            assert desc0 is not None and desc1 is not None, "layer 0 sets the descriptors"
            desc0, desc1 = _layer(model, i, desc0, desc1, encoding0, encoding1, cross_attention)
        if i == conf.n_layers - 1:
            continue  # no early stopping or adaptive width at the last layer
        token0 = token1 = None
        if do_early_stop:
            token0, token1 = model.token_confidence[i](desc0, desc1)
            if model.check_if_stop(token0, token1, i, m + n):
                break
        if do_point_pruning and desc0.shape[-2] > pruning_th:
            desc0, encoding0, ind0 = _prune(model, i, token0, desc0, encoding0, ind0)
        if do_point_pruning and desc1.shape[-2] > pruning_th:
            desc1, encoding1, ind1 = _prune(model, i, token1, desc1, encoding1, ind1)
    assert desc0 is not None and desc1 is not None, "LightGlue has at least one layer"
    if desc0.shape[-2] == 0 or desc1.shape[-2] == 0:  # pruning removed every point of one image
        return torch.zeros((0, 2), dtype=torch.long, device=device), torch.zeros(0, device=device)
    scores, _ = model.log_assignment[i](desc0, desc1)
    matches0, _, match_scores0, _ = filter_matches(scores, conf.filter_threshold)
    valid = matches0[0] > -1
    indices0 = torch.where(valid)[0]
    indices1 = matches0[0][valid]
    matches = torch.stack([ind0[0, indices0], ind1[0, indices1]], -1)
    return matches, match_scores0[0][valid]
