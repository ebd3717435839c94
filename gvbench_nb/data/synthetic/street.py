"""The synthetic street: textured planar façades, ground and street furniture along a route,
with a block of buildings repeated elsewhere (the look-alikes a verifier must reject).
"""

from __future__ import annotations

import functools
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace
from typing import cast

import cv2
import numpy as np

# Pose-rule thresholds.  GV-Bench uses 25 m / 40 deg for city-scale drives.
# This street is ~3x smaller (18-24 m between façades, 10-18 m buildings,
# 2 m frame spacing), so 25 m would call frames that look at entirely different
# buildings "the same place".  8 m (= 4 frames) keeps a true pair looking at the
# same façades with most of the view shared.  Heading overlap does not depend on
# scene scale: with the ~64 deg horizontal field of view, 40 deg still leaves a
# third of the view shared, so GV-Bench's heading threshold is kept.
DEFAULT_MAX_DISTANCE_M = 8.0
DEFAULT_MAX_HEADING_DEG = 40.0


def _low_contrast(name: str, contrast: float) -> str:
    """Texture key for a photograph with reduced contrast (``name@contrast``)."""
    return f"{name}@{contrast:g}"


# Textures (scikit-image photographs that ship with the package, no download).
# ``cat`` is left out: it is the same photograph as ``chelsea``, and a duplicate
# would be aliasing nobody controls.
FACADE_TEXTURES: tuple[str, ...] = (
    "astronaut",
    "brick",
    "camera",
    "chelsea",
    "coffee",
    "coins",
    "horse",
    "moon",
    "page",
    "rocket",
    "text",
    "clock",
    "colorwheel",
    "immunohistochemistry",
    "hubble_deep_field",
    "retina",
    "cell",
)


# Ground textures are the same photograph everywhere, only shifted: two far-apart
# places would show ground patches related by a plane homography, which F-RANSAC
# accepts as geometry.  Real asphalt and paving carry few stable features, so
# the ground keeps only a faint texture.
ROAD_TEXTURE = _low_contrast("gravel", 0.25)


SIDEWALK_TEXTURE = _low_contrast("gravel", 0.4)  # not brick: that is a façade texture


VEGETATION_TEXTURE = "grass"


POLE_TEXTURE = "coins"


TEXTURE_MAX_SIDE = 512


SKY_DEPTH = np.inf


ALIAS_BLOCK_BUILDINGS = 2  # adjacent buildings repeated verbatim elsewhere on the route


@functools.cache
def texture_pyramid(key: str) -> tuple[np.ndarray, ...]:
    """Load a scikit-image photograph as an RGB uint8 mip pyramid.

    ``key`` is a photograph name, optionally ``name@contrast``.  Contrast is
    normalised so dark photographs (moon, hubble) carry as much texture as
    bright ones; the pyramid avoids aliasing on distant surfaces.
    """
    from skimage import data as skdata

    name, _, contrast_text = key.partition("@")
    contrast = float(contrast_text) if contrast_text else 1.0
    image = np.asarray(getattr(skdata, name)())
    if image.dtype == bool:
        # The horse silhouette is binary: soften it so it is not a pure stencil.
        image = cv2.GaussianBlur(image.astype(np.uint8) * 200 + 30, (0, 0), 1.5)
    if image.ndim == 2:
        image = np.repeat(image[:, :, None], 3, axis=2)
    image = image[:, :, :3].astype(np.float32)
    scale = TEXTURE_MAX_SIDE / max(image.shape[:2])
    if scale < 1.0:
        image = cv2.resize(image, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
    luma = image.mean(axis=2)
    image = (image - luma.mean()) * (55.0 * contrast / max(float(luma.std()), 1.0)) + 128.0
    levels = [np.clip(image, 0, 255).astype(np.uint8)]
    while min(levels[-1].shape[:2]) >= 16:
        levels.append(cv2.pyrDown(levels[-1]))
    return tuple(levels)


@dataclass
class Scene:
    """Textured rectangles plus lamp positions and aliasing bookkeeping.

    Rectangle ``i`` spans ``origin[i] + a * edge_u[i] / |edge_u| + b * edge_v[i] / |edge_v|``
    for ``a`` in [0, |edge_u|], ``b`` in [0, |edge_v|] (metres); it is visible
    from the side its normal ``edge_u x edge_v`` points to (one-sided).
    """

    origin: np.ndarray  # (N, 3)
    edge_u: np.ndarray  # (N, 3)
    edge_v: np.ndarray  # (N, 3)
    texture: list[str]  # (N,) texture names
    metres_per_texture: np.ndarray  # (N,) metres covered by the texture width
    texture_offset: np.ndarray  # (N, 2) offset in texture widths (wraps)
    tint: np.ndarray  # (N, 3) RGB multipliers (includes a fixed sun shading)
    lamps: np.ndarray  # (M, 3) world positions of street-lamp heads
    alias_blocks: list[tuple[float, float, float]] = field(default_factory=list)
    """(x of source façade block, x of its copy, block length) along the street."""

    @property
    def normal(self) -> np.ndarray:
        n = np.cross(self.edge_u, self.edge_v)
        return n / np.linalg.norm(n, axis=1, keepdims=True)

    def __len__(self) -> int:
        return len(self.texture)


class _SceneBuilder:
    """Accumulates rectangles; keeps ``build_scene`` readable."""

    SUN_DIRECTION = np.array([0.35, 0.55, 0.76]) / np.linalg.norm([0.35, 0.55, 0.76])

    def __init__(self) -> None:
        self.rects: list[tuple] = []
        self.lamps: list[tuple[float, float, float]] = []

    def add(
        self,
        origin,
        edge_u,
        edge_v,
        texture: str,
        metres_per_texture: float,
        offset: Sequence[float],
        tint: Sequence[float],
    ) -> None:
        origin, edge_u, edge_v = (np.asarray(x, dtype=np.float64) for x in (origin, edge_u, edge_v))
        normal = np.cross(edge_u, edge_v)
        normal /= np.linalg.norm(normal)
        # Fixed directional sun + sky ambient: different façade orientations get
        # different brightness, like a real street at day.
        shade = 0.62 + 0.38 * max(0.0, float(normal @ self.SUN_DIRECTION))
        self.rects.append(
            (origin, edge_u, edge_v, texture, metres_per_texture, tuple(offset), tuple(np.asarray(tint) * shade))
        )

    def add_vertical(
        self, a_xy, b_xy, z0: float, z1: float, facing_xy, texture: str, metres_per_texture: float, offset, tint
    ) -> None:
        """Vertical rectangle over the ground segment a-b, visible from ``facing_xy``."""
        a = np.array([a_xy[0], a_xy[1], z0], dtype=np.float64)
        b = np.array([b_xy[0], b_xy[1], z0], dtype=np.float64)
        up = np.array([0.0, 0.0, z1 - z0])
        normal = np.cross(b - a, up)
        to_viewer = np.array([facing_xy[0], facing_xy[1], z0]) - a
        if normal @ to_viewer < 0:  # flip so the visible side faces the viewer
            a, b = b, a
        self.add(a, b - a, up, texture, metres_per_texture, offset, tint)

    def add_ground(
        self,
        x0: float,
        x1: float,
        y0: float,
        y1: float,
        z: float,
        texture: str,
        metres_per_texture: float,
        offset,
        tint,
    ) -> None:
        self.add([x0, y0, z], [x1 - x0, 0, 0], [0, y1 - y0, 0], texture, metres_per_texture, offset, tint)

    def build(self, alias_blocks) -> Scene:
        origin, edge_u, edge_v, texture, mpt, offset, tint = zip(*self.rects)
        return Scene(
            origin=np.array(origin),
            edge_u=np.array(edge_u),
            edge_v=np.array(edge_v),
            texture=list(texture),
            metres_per_texture=np.array(mpt, dtype=np.float64),
            texture_offset=np.array(offset, dtype=np.float64),
            tint=np.array(tint, dtype=np.float32),
            lamps=np.array(self.lamps, dtype=np.float64).reshape(-1, 3),
            alias_blocks=list(alias_blocks),
        )


@dataclass(frozen=True)
class _Lot:
    """One building (or a side-street gap) along one side of the street."""

    length: float
    is_gap: bool
    setback: float = 0.0
    height: float = 0.0
    texture: str = ""
    metres_per_texture: float = 6.0
    offset: tuple[float, float] = (0.0, 0.0)
    tint: tuple[float, float, float] = (1.0, 1.0, 1.0)
    hedge: bool = False


MAX_SETBACK_M = 12.5  # façades stand 8.5-12.5 m from the street centre line


SIDEWALK_OUTER_M = MAX_SETBACK_M + 0.5


def _random_building(rng: np.random.Generator) -> _Lot:
    return _Lot(
        length=float(rng.uniform(9.0, 17.0)),
        is_gap=False,
        setback=float(rng.uniform(8.5, MAX_SETBACK_M)),
        height=float(rng.uniform(7.0, 16.0)),
        texture=str(rng.choice(FACADE_TEXTURES)),
        metres_per_texture=float(rng.uniform(5.0, 9.0)),
        offset=(float(rng.uniform()), float(rng.uniform())),
        tint=cast(
            tuple[float, float, float],  # size=3: one factor per RGB channel
            tuple(float(c) for c in rng.uniform(0.85, 1.05) * rng.uniform(0.9, 1.05, size=3)),
        ),
        hedge=bool(rng.uniform() < 0.3),
    )


def _street_side_lots(
    rng: np.random.Generator, x_start: float, x_end: float, copies: Mapping[float, list[_Lot]]
) -> list[tuple[float, _Lot]]:
    """Buildings and side-street gaps along one side, as (x_start, lot).

    ``copies`` maps an x position to a block of lots to repeat there verbatim
    (the aliasing copy): it is placed at the first lot boundary past that x.
    """
    lots: list[tuple[float, _Lot]] = []
    pending = sorted(copies.items())
    x = x_start
    next_gap = x + rng.uniform(25.0, 45.0)
    while x < x_end:
        if pending and x >= pending[0][0]:
            for lot in pending.pop(0)[1]:
                lots.append((x, lot))
                x += lot.length
            continue
        if x >= next_gap:
            lot = _Lot(length=float(rng.uniform(9.0, 12.0)), is_gap=True)
            next_gap = x + lot.length + rng.uniform(35.0, 60.0)
        else:
            lot = _random_building(rng)
        lots.append((x, lot))
        x += lot.length
    return lots


def _add_lots(builder: _SceneBuilder, lots: list[tuple[float, _Lot]], side: float, rng: np.random.Generator) -> None:
    """Façades, end walls, hedges and the backdrop seen through side streets."""
    back_depth = 14.0
    for x0, lot in lots:
        x1 = x0 + lot.length
        street = (0.5 * (x0 + x1), 0.0)
        if lot.is_gap:
            # Side-street ground and the backdrop building at its end.
            y_back = side * 34.0
            y_in, y_out = sorted((side * SIDEWALK_OUTER_M, side * 36.0))
            builder.add_ground(
                x0 - 8, x1 + 8, y_in, y_out, 0.0, SIDEWALK_TEXTURE, 4.0, rng.uniform(size=2), (0.85, 0.8, 0.75)
            )
            builder.add_vertical(
                (x0 - 8, y_back),
                (x1 + 8, y_back),
                0.0,
                14.0,
                street,
                lot.texture or FACADE_TEXTURES[0],
                8.0,
                rng.uniform(size=2),
                rng.uniform(0.7, 1.0, size=3),
            )
            continue
        y = side * lot.setback
        y_back = side * (lot.setback + back_depth)
        builder.add_vertical(
            (x0, y), (x1, y), 0.0, lot.height, street, lot.texture, lot.metres_per_texture, lot.offset, lot.tint
        )
        # End walls: visible where a neighbour is set further back or across a gap.
        wall_tint = np.asarray(lot.tint) * 0.85
        builder.add_vertical(
            (x0, y),
            (x0, y_back),
            0.0,
            lot.height,
            (x0 - 1.0, y),
            lot.texture,
            lot.metres_per_texture,
            (lot.offset[0] + 0.37, lot.offset[1]),
            wall_tint,
        )
        builder.add_vertical(
            (x1, y),
            (x1, y_back),
            0.0,
            lot.height,
            (x1 + 1.0, y),
            lot.texture,
            lot.metres_per_texture,
            (lot.offset[0] + 0.61, lot.offset[1]),
            wall_tint,
        )
        if lot.hedge:
            y_hedge = side * (lot.setback - 0.8)
            builder.add_vertical(
                (x0 + 1.0, y_hedge),
                (x1 - 1.0, y_hedge),
                0.0,
                1.3,
                street,
                VEGETATION_TEXTURE,
                3.0,
                (lot.offset[1], 0.3),
                (0.45, 0.85, 0.35),
            )


def _add_ground(builder: _SceneBuilder, x_start: float, x_end: float, rng: np.random.Generator) -> None:
    """Road, sidewalks and open ground in 12 m patches with independent texture
    offsets, so the ground is not exactly periodic along the street (ground
    textures are also faint, see ``ROAD_TEXTURE``)."""
    patch = 12.0
    for x0 in np.arange(x_start, x_end, patch):
        x1 = x0 + patch
        builder.add_ground(x0, x1, -7.0, 7.0, 0.0, ROAD_TEXTURE, 6.0, rng.uniform(size=2), (0.55, 0.55, 0.58))
        for side in (1.0, -1.0):
            # Up to just behind the deepest façade; side streets add their own ground.
            y_in, y_out = sorted((side * 7.0, side * SIDEWALK_OUTER_M))
            builder.add_ground(x0, x1, y_in, y_out, 0.0, SIDEWALK_TEXTURE, 4.0, rng.uniform(size=2), (0.85, 0.8, 0.75))
    # Dashed centre line: strong, periodic road marking.
    for x0 in np.arange(x_start, x_end, 9.0):
        builder.add_ground(x0, x0 + 3.0, -0.08, 0.08, 0.01, "page", 50.0, (0.0, 0.0), (2.2, 2.2, 2.1))


def _add_street_furniture(builder: _SceneBuilder, x_start: float, x_end: float, rng: np.random.Generator) -> None:
    """Lamp posts (whose heads light the night) and street trees."""
    for side, phase in ((1.0, 0.0), (-1.0, 10.0)):
        for x in np.arange(x_start + phase, x_end, 20.0):
            y = side * 7.4
            builder.add_vertical(
                (x - 0.12, y),
                (x + 0.12, y),
                0.0,
                5.6,
                (x, 0.0),
                POLE_TEXTURE,
                2.0,
                rng.uniform(size=2),
                (0.35, 0.35, 0.38),
            )
            builder.lamps.append((float(x), float(side * 6.6), 5.5))
        for x in np.arange(x_start + phase + 7.0, x_end, 20.0):
            if rng.uniform() < 0.5:
                continue
            y = side * 7.9
            builder.add_vertical(
                (x - 0.15, y), (x + 0.15, y), 0.0, 2.6, (x, 0.0), "gravel", 2.0, rng.uniform(size=2), (0.45, 0.35, 0.25)
            )
            width = float(rng.uniform(2.5, 4.0))
            builder.add_vertical(
                (x - width / 2, y),
                (x + width / 2, y),
                2.4,
                2.4 + width * 1.2,
                (x, 0.0),
                VEGETATION_TEXTURE,
                3.0,
                rng.uniform(size=2),
                (0.4, 0.8, 0.3),
            )


def _block_at(x: float, block: list[_Lot]) -> list[tuple[float, _Lot]]:
    """Consecutive lots starting at ``x``."""
    starts = x + np.cumsum([0.0] + [lot.length for lot in block[:-1]])
    return [(float(s), lot) for s, lot in zip(starts, block)]


def _assign_facade_textures(
    rng: np.random.Generator, sides: list[list[tuple[float, _Lot]]], alias_block: list[_Lot]
) -> list[list[tuple[float, _Lot]]]:
    """Give every lot (buildings and side-street backdrops) a texture from a
    shuffled cycle in street order, so a texture recurs only every ~15 lots
    (~100 m): accidental repeats would be uncontrolled aliasing.  The aliased
    buildings keep their own textures, used nowhere else."""
    reserved = {lot.texture for lot in alias_block}
    cycle = [str(t) for t in rng.permutation(FACADE_TEXTURES) if t not in reserved]
    order = sorted(
        (x, side, j)
        for side, lots in enumerate(sides)
        for j, (x, lot) in enumerate(lots)
        if not any(lot is aliased for aliased in alias_block)
    )
    result = [list(lots) for lots in sides]
    for n, (x, side, j) in enumerate(order):
        result[side][j] = (x, replace(result[side][j][1], texture=cycle[n % len(cycle)]))
    return result


def build_scene(route_length_m: float, seed: int = 0) -> Scene:
    """Street scene covering a route from x=0 to ``route_length_m`` (plus look-ahead).

    A block of ``ALIAS_BLOCK_BUILDINGS`` left-side buildings is repeated
    verbatim at a far-apart place along the route (perceptual aliasing); the
    neighbours and the right side differ there, as in real look-alike places.
    """
    rng = np.random.default_rng([seed, 1])
    x_start, x_end = -25.0, route_length_m + 100.0
    builder = _SceneBuilder()

    # Aliasing: a block of left-side buildings starting after x=12 recurs half
    # a route further on, and at least one pose threshold past its own end.
    alias_block = [_random_building(rng) for _ in range(ALIAS_BLOCK_BUILDINGS)]
    block_length = sum(lot.length for lot in alias_block)
    left_lots = _street_side_lots(rng, x_start, 12.0, {})
    source_x = left_lots[-1][0] + left_lots[-1][1].length
    left_lots += _block_at(source_x, alias_block)
    source_end = source_x + block_length
    copy_x = max(source_end + DEFAULT_MAX_DISTANCE_M, source_x + 0.5 * route_length_m)
    left_lots += _street_side_lots(rng, source_end, x_end, {copy_x: alias_block})
    right_lots = _street_side_lots(rng, x_start, x_end, {})
    left_lots, right_lots = _assign_facade_textures(rng, [left_lots, right_lots], alias_block)
    copy_start = [x for x, lot in left_lots if lot is alias_block[0]][1]

    _add_lots(builder, left_lots, 1.0, rng)
    _add_lots(builder, right_lots, -1.0, rng)
    _add_ground(builder, x_start, x_end, rng)
    _add_street_furniture(builder, x_start, x_end, rng)
    # Far end of the street, so looking ahead never shows an empty horizon.
    builder.add_vertical(
        (x_end, -40.0), (x_end, 40.0), 0.0, 20.0, (0.0, 0.0), "hubble_deep_field", 20.0, (0.0, 0.0), (0.8, 0.8, 0.9)
    )
    return builder.build([(source_x, copy_start, block_length)])
