"""The synthetic street: textured rectangles (façades, ground, street furniture) along a route,
with a block of buildings repeated elsewhere (the look-alikes a verifier must reject)."""

from __future__ import annotations

import functools
from collections.abc import Mapping
from dataclasses import dataclass, field, replace

import cv2
import numpy as np

# GV-Bench's 25 m suits city drives; this street is ~3x smaller, so 8 m (4 frames) keeps a true
# pair on the same façades. Heading overlap is scale-free: 40 deg leaves a third of the view shared.
DEFAULT_MAX_DISTANCE_M = 8.0
DEFAULT_MAX_HEADING_DEG = 40.0

# scikit-image photographs (no download); ``cat`` is left out, it duplicates ``chelsea``.
FACADE_TEXTURES: tuple[str, ...] = tuple(
    "astronaut brick camera chelsea coffee coins horse moon page rocket text clock colorwheel "  # noqa: SIM905
    "immunohistochemistry hubble_deep_field retina cell".split()
)
# The ground is one faint photograph (``name@contrast``) shifted everywhere: textured ground at
# two far-apart places would be related by a homography, which F-RANSAC accepts.
ROAD, SIDEWALK = ("gravel@0.25", 6.0), ("gravel@0.4", 4.0)  # texture, metres per texture width
SIDEWALK_TINT = (0.85, 0.8, 0.75)
VEGETATION_TEXTURE = "grass"
TEXTURE_MAX_SIDE = 512
ALIAS_BLOCK_BUILDINGS = 2  # adjacent buildings repeated verbatim elsewhere on the route
MAX_SETBACK_M = 12.5  # façades stand 8.5-12.5 m from the street centre line
SIDEWALK_OUTER_M = MAX_SETBACK_M + 0.5
SUN_DIRECTION = np.array([0.35, 0.55, 0.76]) / np.linalg.norm([0.35, 0.55, 0.76])


@functools.cache
def texture_pyramid(key: str) -> tuple[np.ndarray, ...]:
    """RGB uint8 mip pyramid of a photograph (``name`` or ``name@contrast``), contrast-normalised
    so dark photographs carry as much texture as bright ones."""
    from skimage import data as skdata

    name, _, contrast_text = key.partition("@")
    contrast = float(contrast_text) if contrast_text else 1.0
    image = np.asarray(getattr(skdata, name)())
    if image.dtype == bool:  # the horse silhouette: soften it so it is not a pure stencil
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
    """One-sided textured rectangles ``origin + a * edge_u + b * edge_v`` (a, b in [0, 1]), seen
    from the side ``edge_u x edge_v`` points to, plus the lamps and the repeated façade block."""

    origin: np.ndarray  # (N, 3)
    edge_u: np.ndarray  # (N, 3)
    edge_v: np.ndarray  # (N, 3)
    texture: list[str]  # (N,) texture keys
    metres_per_texture: np.ndarray  # (N,) metres covered by the texture width
    texture_offset: np.ndarray  # (N, 2) offset in texture widths (wraps)
    tint: np.ndarray  # (N, 3) RGB multipliers (includes a fixed sun shading)
    lamps: np.ndarray  # (M, 3) world positions of street-lamp heads
    alias_blocks: list[tuple[float, float, float]] = field(default_factory=list)  # source x, copy x, length

    @property
    def normal(self) -> np.ndarray:
        n = np.cross(self.edge_u, self.edge_v)
        return n / np.linalg.norm(n, axis=1, keepdims=True)


class _SceneBuilder:
    """Accumulates rectangles, each with its material: texture, metres per texture, offset, tint."""

    def __init__(self) -> None:
        self.rects: list[tuple] = []
        self.lamps: list[tuple[float, float, float]] = []

    def add(self, origin, edge_u, edge_v, texture: str, metres_per_texture: float, offset, tint) -> None:
        origin, edge_u, edge_v = (np.asarray(x, dtype=np.float64) for x in (origin, edge_u, edge_v))
        normal = np.cross(edge_u, edge_v)
        normal /= np.linalg.norm(normal)
        # Directional sun plus sky ambient: façade orientations differ in brightness, as by day.
        shade = 0.62 + 0.38 * max(0.0, float(normal @ SUN_DIRECTION))
        self.rects.append(
            (origin, edge_u, edge_v, texture, metres_per_texture, tuple(offset), tuple(np.asarray(tint) * shade))
        )

    def vertical(self, a_xy, b_xy, z0: float, z1: float, facing_xy, *material) -> None:
        """Vertical rectangle over the ground segment a-b, visible from ``facing_xy``."""
        a = np.array([a_xy[0], a_xy[1], z0], dtype=np.float64)
        b = np.array([b_xy[0], b_xy[1], z0], dtype=np.float64)
        up = np.array([0.0, 0.0, z1 - z0])
        if np.cross(b - a, up) @ (np.array([facing_xy[0], facing_xy[1], z0]) - a) < 0:
            a, b = b, a  # flip so the visible side faces the viewer
        self.add(a, b - a, up, *material)

    def ground(self, x0: float, x1: float, y0: float, y1: float, z: float, *material) -> None:
        self.add([x0, y0, z], [x1 - x0, 0, 0], [0, y1 - y0, 0], *material)

    def build(self, alias_blocks) -> Scene:
        origin, edge_u, edge_v, texture, metres, offsets, tint = zip(*self.rects)
        geometry = (np.array(origin), np.array(edge_u), np.array(edge_v), list(texture))
        floats = (np.array(metres, dtype=np.float64), np.array(offsets, dtype=np.float64))
        lamps = np.array(self.lamps, dtype=np.float64).reshape(-1, 3)
        return Scene(*geometry, *floats, np.array(tint, dtype=np.float32), lamps, list(alias_blocks))


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
    tint: tuple[float, ...] = (1.0, 1.0, 1.0)
    hedge: bool = False


def _random_building(rng: np.random.Generator) -> _Lot:
    return _Lot(
        length=float(rng.uniform(9.0, 17.0)),
        is_gap=False,
        setback=float(rng.uniform(8.5, MAX_SETBACK_M)),
        height=float(rng.uniform(7.0, 16.0)),
        texture=str(rng.choice(FACADE_TEXTURES)),
        metres_per_texture=float(rng.uniform(5.0, 9.0)),
        offset=(float(rng.uniform()), float(rng.uniform())),
        tint=tuple(float(c) for c in rng.uniform(0.85, 1.05) * rng.uniform(0.9, 1.05, size=3)),
        hedge=bool(rng.uniform() < 0.3),
    )


def _street_side_lots(
    rng: np.random.Generator, x_start: float, x_end: float, copies: Mapping[float, list[_Lot]]
) -> list[tuple[float, _Lot]]:
    """(x_start, lot) of buildings and side-street gaps along one side; ``copies`` maps an x to a
    block repeated verbatim from the first lot boundary past it."""
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
    """Façades, end walls, hedges, and the side-street ground and backdrop in gaps."""
    for x0, lot in lots:
        x1 = x0 + lot.length
        street = (0.5 * (x0 + x1), 0.0)
        if lot.is_gap:
            y_in, y_out = sorted((side * SIDEWALK_OUTER_M, side * 36.0))
            builder.ground(x0 - 8, x1 + 8, y_in, y_out, 0.0, *SIDEWALK, rng.uniform(size=2), SIDEWALK_TINT)
            end = ((x0 - 8, side * 34.0), (x1 + 8, side * 34.0), 0.0, 14.0, street, lot.texture, 8.0)
            builder.vertical(*end, rng.uniform(size=2), rng.uniform(0.7, 1.0, size=3))
            continue
        y, y_back = side * lot.setback, side * (lot.setback + 14.0)
        material = (lot.texture, lot.metres_per_texture)
        builder.vertical((x0, y), (x1, y), 0.0, lot.height, street, *material, lot.offset, lot.tint)
        # End walls: visible where a neighbour is set further back or across a gap.
        for x, outwards, shift in ((x0, -1.0, 0.37), (x1, 1.0, 0.61)):
            offset = (lot.offset[0] + shift, lot.offset[1])
            wall = ((x, y), (x, y_back), 0.0, lot.height, (x + outwards, y), *material, offset)
            builder.vertical(*wall, np.asarray(lot.tint) * 0.85)
        if lot.hedge:
            y_hedge = side * (lot.setback - 0.8)
            hedge = ((x0 + 1.0, y_hedge), (x1 - 1.0, y_hedge), 0.0, 1.3, street, VEGETATION_TEXTURE, 3.0)
            builder.vertical(*hedge, (lot.offset[1], 0.3), (0.45, 0.85, 0.35))


def _add_ground(builder: _SceneBuilder, x_start: float, x_end: float, rng: np.random.Generator) -> None:
    """Road and sidewalks in 12 m patches with their own texture offsets (not periodic), and the
    dashed centre line (strong, periodic)."""
    for x0 in np.arange(x_start, x_end, 12.0):
        x1 = x0 + 12.0
        builder.ground(x0, x1, -7.0, 7.0, 0.0, *ROAD, rng.uniform(size=2), (0.55, 0.55, 0.58))
        for side in (1.0, -1.0):  # up to just behind the deepest façade
            y_in, y_out = sorted((side * 7.0, side * SIDEWALK_OUTER_M))
            builder.ground(x0, x1, y_in, y_out, 0.0, *SIDEWALK, rng.uniform(size=2), SIDEWALK_TINT)
    for x0 in np.arange(x_start, x_end, 9.0):
        builder.ground(x0, x0 + 3.0, -0.08, 0.08, 0.01, "page", 50.0, (0.0, 0.0), (2.2, 2.2, 2.1))


def _add_street_furniture(builder: _SceneBuilder, x_start: float, x_end: float, rng: np.random.Generator) -> None:
    """Lamp posts (whose heads light the night) and street trees."""
    for side, phase in ((1.0, 0.0), (-1.0, 10.0)):
        for x in np.arange(x_start + phase, x_end, 20.0):
            pole = ((x - 0.12, side * 7.4), (x + 0.12, side * 7.4), 0.0, 5.6, (x, 0.0), "coins", 2.0)
            builder.vertical(*pole, rng.uniform(size=2), (0.35, 0.35, 0.38))
            builder.lamps.append((float(x), float(side * 6.6), 5.5))
        for x in np.arange(x_start + phase + 7.0, x_end, 20.0):
            if rng.uniform() < 0.5:
                continue
            y = side * 7.9
            trunk = ((x - 0.15, y), (x + 0.15, y), 0.0, 2.6, (x, 0.0), "gravel", 2.0)
            builder.vertical(*trunk, rng.uniform(size=2), (0.45, 0.35, 0.25))
            width = float(rng.uniform(2.5, 4.0))
            crown = ((x - width / 2, y), (x + width / 2, y), 2.4, 2.4 + width * 1.2, (x, 0.0), VEGETATION_TEXTURE, 3.0)
            builder.vertical(*crown, rng.uniform(size=2), (0.4, 0.8, 0.3))


def _assign_facade_textures(
    rng: np.random.Generator, sides: list[list[tuple[float, _Lot]]], alias_block: list[_Lot]
) -> list[list[tuple[float, _Lot]]]:
    """Textures from a shuffled cycle in street order, so one recurs only every ~100 m (repeats
    would be uncontrolled aliasing); the aliased buildings keep textures used nowhere else."""
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
    """Street covering x=0 to ``route_length_m`` (plus look-ahead). A block of left-side buildings
    recurs verbatim far along the route, among different neighbours, as look-alike places do."""
    rng = np.random.default_rng([seed, 1])
    x_start, x_end = -25.0, route_length_m + 100.0
    builder = _SceneBuilder()
    # The block starts after x=12 and recurs half a route on, at least one pose threshold past its end.
    alias_block = [_random_building(rng) for _ in range(ALIAS_BLOCK_BUILDINGS)]
    block_length = sum(lot.length for lot in alias_block)
    left_lots = _street_side_lots(rng, x_start, 12.0, {})
    source_x = left_lots[-1][0] + left_lots[-1][1].length
    starts = source_x + np.cumsum([0.0] + [lot.length for lot in alias_block[:-1]])
    left_lots += [(float(s), lot) for s, lot in zip(starts, alias_block)]
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
    end = ((x_end, -40.0), (x_end, 40.0), 0.0, 20.0, (0.0, 0.0), "hubble_deep_field", 20.0)
    builder.vertical(*end, (0.0, 0.0), (0.8, 0.8, 0.9))
    return builder.build([(source_x, copy_start, block_length)])
