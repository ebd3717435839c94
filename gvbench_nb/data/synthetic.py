"""Deterministic synthetic street route for geometric-verification studies.

The generator renders a non-planar street (façades at several setbacks on both
sides, side streets, a textured ground plane, hedges, trees and lamp posts)
textured with the real photographs bundled in scikit-image, from several
traversals of the same route with exact 6-DoF poses.  Conditions
(``illumination``, ``season``, ``weather``) are applied per traversal with a
strength in [0, 1].  Pairs are labelled by the GV-Bench pose rule (distance
and heading thresholds) and written in the GV-Bench pair-file format.

Conventions
-----------
* World frame: X along the street (forward), Y to the left, Z up; metres.
* Camera frame (OpenCV): x right, y down, z forward.  A pose is the
  camera-to-world rotation ``R`` and the camera centre ``t`` so that
  ``X_world = R @ X_cam + t``.
* Pixel (col, row) has its centre at image coordinate (u, v) = (col, row).
* ``depth`` maps hold the camera z-depth in metres (``inf`` for sky);
  ``normals`` maps hold unit world-frame normals (zero for sky).

Rendering is vectorised ray casting against textured rectangles: each
rectangle's inverse depth is linear in (u, v), so a z-buffer pass costs a few
array operations over the rectangle's screen bounding box, and texturing is
one ``cv2.remap`` per (rectangle, mip level).
"""

from __future__ import annotations

import csv
import functools
import json
import math
import os
from collections.abc import Mapping, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import cast

import cv2
import numpy as np

from gvbench_nb.data.sequences import write_pairs

__all__ = [
    "CONDITIONS",
    "DEFAULT_MAX_DISTANCE_M",
    "DEFAULT_MAX_HEADING_DEG",
    "DEFAULT_NIGHT_CONDITIONS",
    "Scene",
    "Traversal",
    "RenderedFrame",
    "default_intrinsics",
    "build_scene",
    "camera_rotation",
    "heading_from_rotation",
    "make_traversal",
    "render_frame",
    "render_traversal",
    "apply_conditions",
    "heading_difference_deg",
    "pose_rule_labels",
    "select_pairs",
    "look_alike_labels",
    "fundamental_from_poses",
    "Route",
    "make_route",
    "write_traversal_images",
    "generate_sample",
]

GENERATOR_VERSION = 1

CONDITIONS: tuple[str, ...] = ("illumination", "season", "weather")

# Pose-rule thresholds.  GV-Bench uses 25 m / 40 deg for city-scale drives.
# This street is ~3x smaller (18-24 m between façades, 10-18 m buildings,
# 2 m frame spacing), so 25 m would call frames that look at entirely different
# buildings "the same place".  8 m (= 4 frames) keeps a true pair looking at the
# same façades with most of the view shared.  Heading overlap does not depend on
# scene scale: with the ~64 deg horizontal field of view, 40 deg still leaves a
# third of the view shared, so GV-Bench's heading threshold is kept.
DEFAULT_MAX_DISTANCE_M = 8.0
DEFAULT_MAX_HEADING_DEG = 40.0

DEFAULT_NIGHT_CONDITIONS: dict[str, float] = {"illumination": 0.7}


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


# ----------------------------------------------------------------------------
# Textures
# ----------------------------------------------------------------------------


@functools.cache
def _texture_pyramid(key: str) -> tuple[np.ndarray, ...]:
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


# ----------------------------------------------------------------------------
# Scene
# ----------------------------------------------------------------------------


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


# ----------------------------------------------------------------------------
# Cameras and traversals
# ----------------------------------------------------------------------------


def default_intrinsics(image_size: tuple[int, int] = (640, 480)) -> np.ndarray:
    """Pinhole K with a ~64 deg horizontal field of view for (width, height)."""
    width, height = image_size
    focal = 0.8 * width
    return np.array([[focal, 0.0, (width - 1) / 2.0], [0.0, focal, (height - 1) / 2.0], [0.0, 0.0, 1.0]])


def camera_rotation(yaw_deg: float, pitch_deg: float = 0.0, roll_deg: float = 0.0) -> np.ndarray:
    """Camera-to-world rotation for a heading (yaw about world Z, 0 = +X), pitch
    (positive looks up) and roll (about the optical axis)."""
    yaw, pitch, roll = np.deg2rad([yaw_deg, pitch_deg, roll_deg])
    # Camera axes at yaw 0: x_cam -> -Y (right), y_cam -> -Z (down), z_cam -> +X.
    base = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
    cz, sz = math.cos(yaw), math.sin(yaw)
    cp, sp = math.cos(pitch), math.sin(pitch)
    cr, sr = math.cos(roll), math.sin(roll)
    rot_yaw = np.array([[cz, -sz, 0.0], [sz, cz, 0.0], [0.0, 0.0, 1.0]])
    rot_pitch = np.array([[1.0, 0.0, 0.0], [0.0, cp, -sp], [0.0, sp, cp]])
    rot_roll = np.array([[cr, -sr, 0.0], [sr, cr, 0.0], [0.0, 0.0, 1.0]])
    return rot_yaw @ base @ rot_pitch @ rot_roll


def heading_from_rotation(rotation: np.ndarray) -> np.ndarray:
    """Heading in degrees (0 = +X, counter-clockwise) of the optical axis."""
    forward = np.asarray(rotation)[..., :, 2]
    return np.rad2deg(np.arctan2(forward[..., 1], forward[..., 0]))


@dataclass
class Traversal:
    """Exact camera poses of one drive along the route."""

    positions: np.ndarray  # (N, 3) camera centres, world frame
    rotations: np.ndarray  # (N, 3, 3) camera-to-world
    yaw_deg: np.ndarray
    pitch_deg: np.ndarray
    roll_deg: np.ndarray

    def __len__(self) -> int:
        return len(self.positions)


def _smooth_noise(rng: np.random.Generator, n: int, amplitude: float, correlation: float = 4.0) -> np.ndarray:
    """Slowly varying jitter (a driver does not zig-zag frame to frame)."""
    white = rng.normal(size=n + 16)
    kernel = np.exp(-0.5 * (np.arange(-8, 9) / correlation) ** 2)
    smooth = np.convolve(white, kernel / np.linalg.norm(kernel), mode="same")[8 : 8 + n]
    return amplitude * smooth


def make_traversal(
    n_frames: int,
    spacing_m: float = 2.0,
    lateral_offset_m: float = 0.0,
    heading_offset_deg: float = 0.0,
    along_offset_m: float = 0.0,
    camera_height_m: float = 1.7,
    seed: int = 0,
    traversal_index: int = 0,
) -> Traversal:
    """Forward drive along +X with a per-traversal offset and smooth pose jitter."""
    rng = np.random.default_rng([seed, 2, traversal_index])
    x = along_offset_m + spacing_m * np.arange(n_frames)
    y = lateral_offset_m + _smooth_noise(rng, n_frames, 0.15)
    z = camera_height_m + _smooth_noise(rng, n_frames, 0.03)
    yaw = heading_offset_deg + _smooth_noise(rng, n_frames, 1.5)
    pitch = _smooth_noise(rng, n_frames, 0.6)
    roll = _smooth_noise(rng, n_frames, 0.4)
    rotations = np.stack([camera_rotation(a, b, c) for a, b, c in zip(yaw, pitch, roll)])
    return Traversal(np.stack([x, y, z], axis=1), rotations, yaw, pitch, roll)


# ----------------------------------------------------------------------------
# Rendering
# ----------------------------------------------------------------------------


@dataclass
class RenderedFrame:
    """Clear render plus the per-pixel geometry conditions need."""

    image: np.ndarray  # (H, W, 3) uint8 RGB
    depth: np.ndarray  # (H, W) float32 camera z-depth, inf for sky
    normals: np.ndarray  # (H, W, 3) float32 world-frame unit normals, 0 for sky
    light_points: np.ndarray  # (M, 4) visible lamps: u, v, depth, pool radius px


NEAR_PLANE_M = 0.1


def _clip_polygon_near(points_cam: np.ndarray) -> np.ndarray:
    """Clip a camera-frame polygon to z >= NEAR_PLANE_M (Sutherland-Hodgman)."""
    clipped = []
    n = len(points_cam)
    for i in range(n):
        p, q = points_cam[i], points_cam[(i + 1) % n]
        p_in, q_in = p[2] >= NEAR_PLANE_M, q[2] >= NEAR_PLANE_M
        if p_in:
            clipped.append(p)
        if p_in != q_in:
            s = (NEAR_PLANE_M - p[2]) / (q[2] - p[2])
            clipped.append(p + s * (q - p))
    return np.array(clipped).reshape(-1, 3)


def _screen_bbox(corners_cam: np.ndarray, K: np.ndarray, width: int, height: int):
    """Integer pixel box (c0, r0, c1, r1) covering the rectangle, or None."""
    polygon = _clip_polygon_near(corners_cam)
    if len(polygon) < 3:
        return None
    projected = (K @ polygon.T).T
    uv = projected[:, :2] / projected[:, 2:3]
    c0 = max(int(math.floor(uv[:, 0].min())), 0)
    r0 = max(int(math.floor(uv[:, 1].min())), 0)
    c1 = min(int(math.ceil(uv[:, 0].max())) + 1, width)
    r1 = min(int(math.ceil(uv[:, 1].max())) + 1, height)
    if c0 >= c1 or r0 >= r1:
        return None
    return c0, r0, c1, r1


def _remap_flat(texture: np.ndarray, map_x: np.ndarray, map_y: np.ndarray) -> np.ndarray:
    """cv2.remap for a flat list of coordinates (remap needs < 32767 rows)."""
    n = len(map_x)
    cols = 1024
    rows = -(-n // cols)
    maps = np.zeros((2, rows * cols), dtype=np.float32)
    maps[0, :n] = map_x
    maps[1, :n] = map_y
    out = cv2.remap(
        texture, maps[0].reshape(rows, cols), maps[1].reshape(rows, cols), cv2.INTER_LINEAR, borderMode=cv2.BORDER_WRAP
    )
    return out.reshape(rows * cols, -1)[:n]


def _sky_colour(ray_world: np.ndarray) -> np.ndarray:
    """Smooth blue gradient by elevation (RGB float 0-255)."""
    elevation = np.clip(ray_world[..., 2] / np.linalg.norm(ray_world, axis=-1), 0.0, 1.0)
    horizon = np.array([200.0, 215.0, 230.0], dtype=np.float32)
    zenith = np.array([95.0, 140.0, 205.0], dtype=np.float32)
    weight = np.sqrt(elevation)[..., None].astype(np.float32)
    return horizon * (1 - weight) + zenith * weight


@dataclass
class _PlaneInCamera:
    """A rectangle in camera coordinates, as affine functions of pixel (u, v).

    For ray r = K^-1 [u, v, 1] the hit point is X = r / q with inverse depth
    q = (n . r) / d, and the in-plane coordinates are a = (u_hat . r) / q - u_hat . P0
    (same for b), so every quantity is an affine function of (u, v) or a ratio
    of two.
    """

    q_coef: np.ndarray  # (3,) float32: q = c0 u + c1 v + c2
    a_coef: np.ndarray
    b_coef: np.ndarray
    a_offset: float
    b_offset: float
    u_length: float
    v_length: float
    plane_offset: float  # d = n . P0 (negative: camera on the visible side)

    def inverse_depth(self, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        c = self.q_coef
        return c[0] * u + c[1] * v + c[2]

    def plane_coordinates(self, u: np.ndarray, v: np.ndarray, inv_q: np.ndarray):
        a = (self.a_coef[0] * u + self.a_coef[1] * v + self.a_coef[2]) * inv_q - self.a_offset
        b = (self.b_coef[0] * u + self.b_coef[1] * v + self.b_coef[2]) * inv_q - self.b_offset
        return a, b


def _planes_in_camera(
    scene: Scene, rotation: np.ndarray, position: np.ndarray, K_inv: np.ndarray
) -> tuple[np.ndarray, np.ndarray, list]:
    """Front-facing rectangles: their corners in camera frame and plane functions."""
    R_wc = rotation.T
    origin = (scene.origin - position) @ R_wc.T
    edge_u = scene.edge_u @ R_wc.T
    edge_v = scene.edge_v @ R_wc.T
    u_length = np.linalg.norm(edge_u, axis=1)
    v_length = np.linalg.norm(edge_v, axis=1)
    u_hat, v_hat = edge_u / u_length[:, None], edge_v / v_length[:, None]
    normal = np.cross(u_hat, v_hat)
    plane_offset = np.einsum("ij,ij->i", normal, origin)
    # One-sided: the camera (origin) must be on the side the normal points to.
    front = np.flatnonzero(plane_offset < -1e-6)
    corners = np.stack([origin, origin + edge_u, origin + edge_u + edge_v, origin + edge_v], axis=1)
    planes = []
    for i in front:
        planes.append(
            _PlaneInCamera(
                q_coef=((normal[i] @ K_inv) / plane_offset[i]).astype(np.float32),
                a_coef=(u_hat[i] @ K_inv).astype(np.float32),
                b_coef=(v_hat[i] @ K_inv).astype(np.float32),
                a_offset=float(u_hat[i] @ origin[i]),
                b_offset=float(v_hat[i] @ origin[i]),
                u_length=float(u_length[i]),
                v_length=float(v_length[i]),
                plane_offset=float(plane_offset[i]),
            )
        )
    return front, corners[front], planes


def render_frame(
    scene: Scene, rotation: np.ndarray, position: np.ndarray, K: np.ndarray, image_size: tuple[int, int] = (640, 480)
) -> RenderedFrame:
    """Ray-cast the scene from one camera pose (clear conditions)."""
    width, height = image_size
    K_inv = np.linalg.inv(K)
    front, corners, planes = _planes_in_camera(scene, rotation, position, K_inv)

    # Pass 1: z-buffer on inverse depth, rectangle by rectangle over its screen box.
    inv_depth = np.zeros((height, width), dtype=np.float32)
    rect_id = np.full((height, width), -1, dtype=np.int16 if len(scene) < 32000 else np.int32)
    cols = np.arange(width, dtype=np.float32)
    rows = np.arange(height, dtype=np.float32)
    for k, plane in enumerate(planes):
        box = _screen_bbox(corners[k], K, width, height)
        if box is None:
            continue
        c0, r0, c1, r1 = box
        uu, vv = cols[None, c0:c1], rows[r0:r1, None]
        q = plane.inverse_depth(uu, vv)
        zbuf = inv_depth[r0:r1, c0:c1]
        hit = q > zbuf
        if not hit.any():
            continue
        a, b = plane.plane_coordinates(uu, vv, 1.0 / np.maximum(q, 1e-9))
        hit &= (a >= 0) & (a <= plane.u_length) & (b >= 0) & (b <= plane.v_length)
        zbuf[hit] = q[hit]
        rect_id[r0:r1, c0:c1][hit] = k

    # Pass 2: texture each visible rectangle (pixels grouped by rectangle).
    image: np.ndarray = np.empty((height * width, 3), dtype=np.float32)
    normals = np.zeros((height * width, 3), dtype=np.float32)
    flat_id = rect_id.ravel()
    order = np.argsort(flat_id, kind="stable")
    counts = np.bincount(flat_id.astype(np.int32) + 1, minlength=len(planes) + 1)
    bounds = np.concatenate([[0], np.cumsum(counts)])
    ids = np.flatnonzero(counts) - 1  # -1 is the sky
    ray_norm = np.sqrt(
        ((cols[None, :] - K[0, 2]) / K[0, 0]) ** 2 + ((rows[:, None] - K[1, 2]) / K[1, 1]) ** 2 + 1.0
    ).ravel()
    world_normal = scene.normal.astype(np.float32)
    focal = float(K[0, 0])
    for k in ids.tolist():
        pixels = order[bounds[k + 1] : bounds[k + 2]]
        rr, cc = np.divmod(pixels, width)
        if k < 0:
            pixel_h = np.stack([cc, rr, np.ones_like(cc)], axis=1).astype(np.float32)
            image[pixels] = _sky_colour(pixel_h @ (rotation @ K_inv).T.astype(np.float32))
            continue
        i = front[k]
        image[pixels] = _texture_colours(
            scene, i, planes[k], cc.astype(np.float32), rr.astype(np.float32), ray_norm[pixels], focal
        )
        normals[pixels] = world_normal[i]

    # Mild optical blur: real lenses are not perfectly sharp and it hides
    # the stair-casing of unsupersampled edges.
    image = cv2.GaussianBlur(image.reshape(height, width, 3), (0, 0), 0.6)
    depth = np.where(inv_depth > 0, 1.0 / np.maximum(inv_depth, 1e-12), SKY_DEPTH).astype(np.float32)
    lights = _visible_lamps(scene.lamps, rotation, position, K, depth)
    return RenderedFrame(
        np.clip(np.rint(image), 0, 255).astype(np.uint8), depth, normals.reshape(height, width, 3), lights
    )


def _texture_colours(
    scene: Scene, i: int, plane: _PlaneInCamera, u: np.ndarray, v: np.ndarray, ray_norm: np.ndarray, focal: float
) -> np.ndarray:
    """Tinted texture colours of rectangle ``i`` at pixels (u, v), mip-mapped."""
    q = plane.inverse_depth(u, v)
    a, b = plane.plane_coordinates(u, v, 1.0 / q)
    pyramid = _texture_pyramid(scene.texture[i])
    tex_w = pyramid[0].shape[1]
    texels_per_metre = np.float32(tex_w / scene.metres_per_texture[i])
    # Mip level from the texel footprint of a pixel; obliquity is only half
    # counted (sqrt) so grazing surfaces blur less than isotropic mipmaps would.
    cos_incidence = np.abs(q * np.float32(plane.plane_offset) / ray_norm)
    footprint = texels_per_metre / (q * focal) / np.sqrt(np.maximum(cos_incidence, 0.05))
    level = np.clip(np.rint(np.log2(np.maximum(footprint, 1e-6))), 0, len(pyramid) - 1).astype(np.int8)
    tex_h = pyramid[0].shape[0]
    # Wrap into the base texture (tiling) before scaling to a mip level, so
    # every level tiles with its own size and remap never sees huge coordinates.
    tex_x = np.mod(a * texels_per_metre + np.float32(scene.texture_offset[i, 0] * tex_w), tex_w)
    tex_y = np.mod(np.float32(scene.texture_offset[i, 1] * tex_w) - b * texels_per_metre, tex_h)
    colours = np.empty((len(u), 3), dtype=np.float32)
    for lv in range(int(level.min()), int(level.max()) + 1):
        sel = level == lv
        if not sel.any():
            continue
        tex = pyramid[lv]
        scale_x = np.float32(tex.shape[1] / tex_w)
        scale_y = np.float32(tex.shape[0] / tex_h)
        colours[sel] = _remap_flat(tex, tex_x[sel] * scale_x, tex_y[sel] * scale_y)
    return colours * scene.tint[i]


def _visible_lamps(
    lamps: np.ndarray, rotation: np.ndarray, position: np.ndarray, K: np.ndarray, depth: np.ndarray
) -> np.ndarray:
    """Project lamp heads; keep those in view and not hidden behind a surface."""
    if len(lamps) == 0:
        return np.zeros((0, 4))
    height, width = depth.shape
    cam = (lamps - position) @ rotation
    in_front = cam[:, 2] > 1.0
    cam = cam[in_front]
    uv = (cam @ K.T)[:, :2] / cam[:, 2:3]
    inside = (uv[:, 0] >= 0) & (uv[:, 0] < width) & (uv[:, 1] >= 0) & (uv[:, 1] < height)
    cam, uv = cam[inside], uv[inside]
    surface = depth[uv[:, 1].astype(int), uv[:, 0].astype(int)]
    unoccluded = cam[:, 2] <= surface + 0.5
    pool_radius = K[0, 0] * 4.0 / cam[:, 2]  # ~4 m light pool
    return np.column_stack([uv, cam[:, 2], pool_radius])[unoccluded]


def frame_rng(seed: int, traversal_index: int, frame_index: int) -> np.random.Generator:
    """Independent, reproducible random stream per rendered frame."""
    return np.random.default_rng([seed, 3, traversal_index, frame_index])


def _render_with_conditions(
    scene: Scene,
    traversal: Traversal,
    frame: int,
    K: np.ndarray,
    image_size: tuple[int, int],
    conditions: Mapping[str, float],
    seed: int,
    traversal_index: int,
) -> np.ndarray:
    rendered = render_frame(scene, traversal.rotations[frame], traversal.positions[frame], K, image_size)
    return apply_conditions(
        rendered.image,
        rendered.depth,
        rendered.normals,
        conditions,
        frame_rng(seed, traversal_index, frame),
        light_points=rendered.light_points,
    )


def render_traversal(
    scene: Scene,
    traversal: Traversal,
    K: np.ndarray,
    image_size: tuple[int, int] = (640, 480),
    conditions: Mapping[str, float] | None = None,
    seed: int = 0,
    traversal_index: int = 0,
    workers: int | None = None,
) -> list[np.ndarray]:
    """Render every frame of a traversal under the given conditions (RGB uint8).

    Frames are independent (own random stream), so they are rendered on
    ``workers`` threads (numpy and OpenCV release the GIL); the result does
    not depend on the number of workers.
    """
    conditions = dict(conditions or {})
    _validate_conditions(conditions)
    workers = workers or min(4, os.cpu_count() or 1)

    def render(frame: int) -> np.ndarray:
        return _render_with_conditions(scene, traversal, frame, K, image_size, conditions, seed, traversal_index)

    if workers <= 1:
        return [render(frame) for frame in range(len(traversal))]
    with ThreadPoolExecutor(max_workers=workers) as pool:
        return list(pool.map(render, range(len(traversal))))


# ----------------------------------------------------------------------------
# Conditions
# ----------------------------------------------------------------------------


def _validate_conditions(conditions: Mapping[str, float]) -> dict[str, float]:
    unknown = set(conditions) - set(CONDITIONS)
    if unknown:
        raise ValueError(f"unknown conditions {sorted(unknown)}; known: {CONDITIONS}")
    strengths = {name: float(conditions.get(name, 0.0)) for name in CONDITIONS}
    for name, strength in strengths.items():
        if not 0.0 <= strength <= 1.0:
            raise ValueError(f"condition {name!r} strength {strength} outside [0, 1]")
    return strengths


def _low_frequency_noise(rng: np.random.Generator, shape: tuple[int, int], cells: int = 12) -> np.ndarray:
    """Smooth random field in [0, 1] (snow patchiness)."""
    height, width = shape
    coarse = rng.uniform(size=(cells, max(2, cells * width // height))).astype(np.float32)
    return np.clip(cv2.resize(coarse, (width, height), interpolation=cv2.INTER_CUBIC), 0.0, 1.0)


def _apply_season(
    image: np.ndarray, normals: np.ndarray, depth: np.ndarray, strength: float, rng: np.random.Generator
) -> np.ndarray:
    """Winter: snow on upward-facing surfaces, brown vegetation, pale overcast light."""
    up = np.clip(normals[..., 2], 0.0, 1.0)
    patchiness = _low_frequency_noise(rng, up.shape)
    snow_cover = np.clip(strength * 1.25 * up**2 * (0.65 + 0.45 * patchiness), 0.0, 1.0)
    snow = np.array([236.0, 240.0, 248.0], dtype=np.float32)
    image = image * (1 - snow_cover[..., None]) + snow * snow_cover[..., None]

    red, green, blue = image[..., 0], image[..., 1], image[..., 2]
    greenness = np.clip((green - np.maximum(red, blue)) / 40.0, 0.0, 1.0)
    luma = image @ np.array([0.299, 0.587, 0.114], dtype=np.float32)
    dead_leaves = luma[..., None] * np.array([1.0, 0.88, 0.7], dtype=np.float32)
    weight = (strength * greenness)[..., None]
    image = image * (1 - weight) + dead_leaves * weight

    # Overcast winter light: desaturated, slightly cooler, sky turns white-grey.
    luma = (image @ np.array([0.299, 0.587, 0.114], dtype=np.float32))[..., None]
    image = luma + (image - luma) * (1 - 0.35 * strength)
    image = image * np.array([1 - 0.04 * strength, 1.0, 1 + 0.05 * strength], dtype=np.float32)
    sky = np.isinf(depth)[..., None]
    overcast = np.array([205.0, 208.0, 212.0], dtype=np.float32)
    return np.where(sky, image * (1 - 0.7 * strength) + overcast * 0.7 * strength, image)


def _apply_weather(image: np.ndarray, depth: np.ndarray, strength: float, rng: np.random.Generator) -> np.ndarray:
    """Fog that thickens with depth, rain streaks and a wet, softened lens."""
    extinction_per_m = 0.045 * strength  # visibility ~65 m at full strength
    transmission = np.exp(-extinction_per_m * np.where(np.isinf(depth), 1e4, depth))[..., None]
    airlight = np.float32(185.0 - 25.0 * strength)
    image = image * (1 - 0.12 * strength) * transmission + airlight * (1 - transmission)

    height, width = depth.shape
    streaks: np.ndarray = np.zeros((height, width), dtype=np.float32)
    slant = rng.uniform(-0.25, 0.25)
    n_streaks = int(1800 * strength)
    starts = rng.uniform([0, -30], [width, height], size=(n_streaks, 2))
    lengths = rng.uniform(8, 28, size=n_streaks)
    brightness = rng.uniform(0.3, 1.0, size=n_streaks)
    for (x, y), length, level in zip(starts, lengths, brightness):
        end = (int(x + slant * length), int(y + length))
        cv2.line(streaks, (int(x), int(y)), end, float(level), 1, cv2.LINE_AA)
    streaks = cv2.GaussianBlur(streaks, (0, 0), 0.8)[..., None]
    image = image + (0.55 * strength) * streaks * (235.0 - image)
    sigma = 1.4 * strength
    if sigma > 0.3:
        image = cv2.GaussianBlur(image, (0, 0), sigma)
    return image


def _lamp_fields(depth: np.ndarray, light_points: np.ndarray, downscale: int = 4) -> tuple[np.ndarray, np.ndarray]:
    """Light pools on surfaces near each lamp and the lamps' glare, (H, W) each.

    Both are smooth, so they are computed at 1/``downscale`` resolution.
    """
    height, width = depth.shape
    small_depth = np.where(np.isinf(depth), 1e4, depth)[::downscale, ::downscale]
    rows, cols = np.mgrid[0 : small_depth.shape[0], 0 : small_depth.shape[1]].astype(np.float32)
    rows, cols = rows * downscale, cols * downscale
    pool = np.zeros_like(small_depth)
    glare = np.zeros_like(small_depth)
    for u, v, lamp_depth, radius in np.asarray(light_points, dtype=np.float32).reshape(-1, 4):
        # The pool sits below the lamp head and only on surfaces at its depth.
        distance_sq = (cols - u) ** 2 + (rows - v - 0.6 * radius) ** 2
        near_lamp = np.exp(-np.abs(small_depth - lamp_depth) / 5.0)
        pool += np.exp(-distance_sq / (2 * radius**2)) * near_lamp
        glare_sigma = 3.0 * max(2.0, 0.08 * radius)
        glare += np.exp(-((cols - u) ** 2 + (rows - v) ** 2) / (2 * glare_sigma**2))
    size = (width, height)
    return (
        cv2.resize(pool, size, interpolation=cv2.INTER_LINEAR),
        cv2.resize(glare, size, interpolation=cv2.INTER_LINEAR),
    )


def _apply_illumination(
    image: np.ndarray, depth: np.ndarray, strength: float, rng: np.random.Generator, light_points: np.ndarray | None
) -> np.ndarray:
    """Day -> night: less daylight, headlights and lamps, colour cast, gain noise."""
    height, width = depth.shape
    linear = (image * np.float32(1 / 255.0)) ** np.float32(2.2)
    daylight = math.exp(-4.0 * strength)  # ~6 % of daylight at strength 0.7

    # Headlights of the recording vehicle light the road and near surfaces.
    finite_depth = np.where(np.isinf(depth), 1e4, depth)
    row_weight = np.exp(-((np.arange(height, dtype=np.float32)[:, None] / height - 0.85) ** 2) / 0.12)
    headlight = np.float32(strength * 0.6) * np.exp(-finite_depth / np.float32(8.0)) * row_weight
    if light_points is None:
        light_points = _random_light_points(rng, depth)
    pool, glare = _lamp_fields(depth, light_points)
    warm = np.array([1.0, 0.75, 0.45], dtype=np.float32)  # sodium-lamp orange
    # Auto-exposure raises the gain (and with it the noise); the colour cast is
    # a white balance set for daylight under sodium lamps.
    gain = 1.0 + 3.0 * strength
    gain_rgb = gain * np.array([1 + 0.1 * strength, 1.0, 1 - 0.25 * strength], dtype=np.float32)
    light = headlight[..., None] * np.array([1.0, 0.97, 0.9], dtype=np.float32)
    light += (0.5 * strength * pool)[..., None] * warm
    light += np.float32(daylight)
    light *= gain_rgb
    linear *= light
    # Night sky: dark blue with a faint orange city glow near the horizon.
    sky = np.isinf(depth)
    if sky.any():
        glow = (np.nonzero(sky)[0].astype(np.float32) / height)[:, None]
        night_sky = (
            np.array([0.002, 0.003, 0.008], dtype=np.float32) + np.array([0.012, 0.007, 0.003], dtype=np.float32) * glow
        )
        linear[sky] = linear[sky] * (1 - strength) + night_sky * (strength * gain_rgb)

    # Shot noise grows with signal and gain, read noise with gain only.  Buffers
    # are reused: fresh full-size arrays cost more (page faults) than the maths.
    noise_std = np.multiply(linear, np.float32(strength * 0.002 * gain), out=light)
    noise_std += np.float32((0.006 * strength * gain) ** 2)
    np.sqrt(noise_std, out=noise_std)
    noise = rng.standard_normal(linear.shape, dtype=np.float32)
    noise *= noise_std
    linear += noise
    linear += np.multiply((strength * 2.0 * glare)[..., None], warm, out=noise)
    np.clip(linear, 0.0, None, out=linear)
    np.power(linear, np.float32(1 / 2.2), out=linear)
    linear *= np.float32(255.0)
    return linear


def _random_light_points(rng: np.random.Generator, depth: np.ndarray) -> np.ndarray:
    """Lamp positions when the caller has no scene geometry (image upper half)."""
    height, width = depth.shape
    n = int(rng.integers(1, 5))
    u = rng.uniform(0, width, size=n)
    v = rng.uniform(0, 0.5 * height, size=n)
    lamp_depth = np.minimum(depth[v.astype(int), u.astype(int)], 60.0)
    return np.column_stack([u, v, lamp_depth, 0.6 * width * 4.0 / lamp_depth])


def apply_conditions(
    image: np.ndarray,
    depth: np.ndarray,
    normals: np.ndarray,
    conditions: Mapping[str, float],
    rng: np.random.Generator,
    *,
    light_points: np.ndarray | None = None,
) -> np.ndarray:
    """Apply condition strengths (names in ``CONDITIONS``, values in [0, 1]).

    Conditions compose in a physical order: ``season`` changes surfaces,
    ``weather`` adds the medium (fog, rain) and ``illumination`` last, because
    exposure, gain noise and glare happen in the camera.  A condition at
    strength 0 is skipped, so all-zero strengths return the image unchanged
    (byte-identical copy).  ``light_points`` (M, 4: u, v, depth, pool radius
    in px) places the night lamps; without it they are drawn from ``rng``.
    """
    strengths = _validate_conditions(conditions)
    if all(s == 0.0 for s in strengths.values()):
        return image.copy()
    result = image.astype(np.float32)
    if strengths["season"] > 0:
        result = _apply_season(result, normals, depth, strengths["season"], rng)
    if strengths["weather"] > 0:
        result = _apply_weather(result, depth, strengths["weather"], rng)
    if strengths["illumination"] > 0:
        result = _apply_illumination(np.clip(result, 0, 255), depth, strengths["illumination"], rng, light_points)
    return np.clip(np.rint(result), 0, 255).astype(np.uint8)


# ----------------------------------------------------------------------------
# Labels, pairs and geometry
# ----------------------------------------------------------------------------


def heading_difference_deg(heading_a: np.ndarray, heading_b: np.ndarray) -> np.ndarray:
    """Absolute heading difference wrapped to [0, 180] degrees."""
    diff = np.abs(np.asarray(heading_a, dtype=np.float64) - np.asarray(heading_b, dtype=np.float64)) % 360.0
    return np.minimum(diff, 360.0 - diff)


def pose_rule_labels(
    query_positions: np.ndarray,
    query_headings_deg: np.ndarray,
    reference_positions: np.ndarray,
    reference_headings_deg: np.ndarray,
    max_distance_m: float = DEFAULT_MAX_DISTANCE_M,
    max_heading_deg: float = DEFAULT_MAX_HEADING_DEG,
) -> np.ndarray:
    """GV-Bench pose rule: (Q, R) bool matrix, True where the camera centres are
    within ``max_distance_m`` (3-D Euclidean) and headings within ``max_heading_deg``."""
    query_positions = np.atleast_2d(np.asarray(query_positions, dtype=np.float64))
    reference_positions = np.atleast_2d(np.asarray(reference_positions, dtype=np.float64))
    distance = np.linalg.norm(query_positions[:, None, :] - reference_positions[None, :, :], axis=2)
    heading = heading_difference_deg(
        np.atleast_1d(query_headings_deg)[:, None], np.atleast_1d(reference_headings_deg)[None, :]
    )
    return (distance <= max_distance_m) & (heading <= max_heading_deg)


def _alias_reference_position(scene: Scene, query_x: float, look_ahead_m: float = 15.0) -> float | None:
    """Where the look-alike of what the query sees would be seen from, if any
    (the query has the repeated façade within ``look_ahead_m`` ahead)."""
    for source_x, copy_x, length in scene.alias_blocks:
        shift = copy_x - source_x
        if source_x - look_ahead_m <= query_x <= source_x + 0.5 * length:
            return query_x + shift
        if copy_x - look_ahead_m <= query_x <= copy_x + 0.5 * length:
            return query_x - shift
    return None


LOOK_ALIKE_LOOK_AHEAD_M = 25.0


def look_alike_labels(
    scene: Scene,
    query: Traversal,
    reference: Traversal,
    max_distance_m: float = DEFAULT_MAX_DISTANCE_M,
    max_heading_deg: float = DEFAULT_MAX_HEADING_DEG,
    look_ahead_m: float = LOOK_ALIKE_LOOK_AHEAD_M,
) -> np.ndarray:
    """(Q, R) bool: false pairs whose reference sees the look-alike of what the query sees.

    A pair is a look-alike (aliasing) pair when it is false by the pose rule but
    would be true if the query stood at its look-alike position (its position
    shifted by the repeated façade block's offset, see ``_alias_reference_position``):
    the reference then views the copy of the block the query views from the same
    relative pose, so the two images show the same façades.  ``look_ahead_m`` is
    how far ahead the block may start for the query to count as seeing it.  It is
    wider than the 15 m ``select_pairs`` uses to pick one look-alike a query: on the
    30-frame seed-0 route, query frame 0 stands 15.4 m before the block and its
    look-alike reference scores 147 SIFT inliers, more than most true pairs.
    """
    headings_q = heading_from_rotation(query.rotations)
    headings_r = heading_from_rotation(reference.rotations)
    true_pairs = pose_rule_labels(
        query.positions, headings_q, reference.positions, headings_r, max_distance_m, max_heading_deg
    )
    look_alike = np.zeros_like(true_pairs)
    for qi, position in enumerate(query.positions):
        alias_x = _alias_reference_position(scene, float(position[0]), look_ahead_m)
        if alias_x is None:
            continue
        shifted = position.copy()
        shifted[0] = alias_x
        look_alike[qi] = pose_rule_labels(
            shifted, headings_q[qi : qi + 1], reference.positions, headings_r, max_distance_m, max_heading_deg
        )[0]
    return look_alike & ~true_pairs


def select_pairs(
    scene: Scene,
    query: Traversal,
    reference: Traversal,
    seed: int = 0,
    max_distance_m: float = DEFAULT_MAX_DISTANCE_M,
    max_heading_deg: float = DEFAULT_MAX_HEADING_DEG,
    n_positives: int = 3,
    n_near_negatives: int = 2,
    n_far_negatives: int = 2,
) -> list[tuple[int, int, int]]:
    """Candidate (query, reference, label) triples per query frame.

    Per query: the nearest true reference plus random further true ones, near
    negatives (just beyond the distance threshold: hard, they still overlap),
    far negatives, and the aliasing look-alike when the query sees a repeated
    façade (otherwise one more far negative).  All choices come from ``seed``.
    """
    rng = np.random.default_rng([seed, 4])
    labels = pose_rule_labels(
        query.positions,
        heading_from_rotation(query.rotations),
        reference.positions,
        heading_from_rotation(reference.rotations),
        max_distance_m,
        max_heading_deg,
    )
    distance = np.linalg.norm(query.positions[:, None] - reference.positions[None], axis=2)
    pairs: list[tuple[int, int, int]] = []
    for qi in range(len(query)):
        order = np.argsort(distance[qi], kind="stable")
        positives = [r for r in order if labels[qi, r]]
        negatives = [r for r in order if not labels[qi, r]]
        near = [r for r in negatives if distance[qi, r] <= 2.5 * max_distance_m]
        far = [r for r in negatives if distance[qi, r] > 2.5 * max_distance_m]
        chosen: list[int] = positives[:1]
        chosen += _pick(rng, positives[1:], n_positives - len(chosen))
        chosen += _pick(rng, near, n_near_negatives)
        alias_x = _alias_reference_position(scene, float(query.positions[qi, 0]))
        alias_ref = None
        if alias_x is not None:
            candidate = int(np.argmin(np.abs(reference.positions[:, 0] - alias_x)))
            if not labels[qi, candidate] and candidate not in chosen:
                alias_ref = candidate
        n_far = n_far_negatives + (alias_ref is None)
        chosen += _pick(rng, [r for r in far if r != alias_ref], n_far)
        if alias_ref is not None:
            chosen.append(alias_ref)
        # Short routes lack far negatives: top up with other negatives, then positives.
        target = n_positives + n_near_negatives + n_far_negatives + 1
        for pool in (negatives, positives):
            chosen += _pick(rng, [r for r in pool if r not in chosen], target - len(chosen))
        pairs += [(qi, int(r), int(labels[qi, r])) for r in sorted(set(chosen))]
    return pairs


def _pick(rng: np.random.Generator, candidates: Sequence[int], n: int) -> list[int]:
    """Up to ``n`` distinct candidates drawn without replacement."""
    if n <= 0 or not candidates:
        return []
    idx = rng.choice(len(candidates), size=min(n, len(candidates)), replace=False)
    return [int(candidates[i]) for i in sorted(idx)]


def _skew(vector: np.ndarray) -> np.ndarray:
    x, y, z = vector
    return np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])


def fundamental_from_poses(
    K0: np.ndarray, R0: np.ndarray, t0: np.ndarray, K1: np.ndarray, R1: np.ndarray, t1: np.ndarray
) -> np.ndarray:
    """Fundamental matrix F with ``x1^T F x0 = 0`` (OpenCV's findFundamentalMat(p0, p1)
    convention) from camera-to-world poses (R, t = camera centre)."""
    R0, R1 = np.asarray(R0, dtype=np.float64), np.asarray(R1, dtype=np.float64)
    t0, t1 = np.asarray(t0, dtype=np.float64).ravel(), np.asarray(t1, dtype=np.float64).ravel()
    rotation = R1.T @ R0  # camera 0 -> camera 1
    translation = R1.T @ (t0 - t1)
    essential = _skew(translation) @ rotation
    F = np.linalg.inv(K1).T @ essential @ np.linalg.inv(K0)
    return F / np.linalg.norm(F)


# ----------------------------------------------------------------------------
# Sample generation
# ----------------------------------------------------------------------------

POSE_COLUMNS = [
    "traversal",
    "frame",
    "image",
    "x",
    "y",
    "z",
    "yaw_deg",
    "pitch_deg",
    "roll_deg",
    "fx",
    "fy",
    "cx",
    "cy",
] + [f"r{i}{j}" for i in range(3) for j in range(3)]


def _pose_rows(name: str, traversal: Traversal, K: np.ndarray, image_names: list[str]) -> list[dict]:
    rows = []
    for frame, image_name in enumerate(image_names):
        row = {"traversal": name, "frame": frame, "image": image_name}
        row.update(zip("xyz", (f"{v:.6f}" for v in traversal.positions[frame])))
        row.update(
            yaw_deg=f"{traversal.yaw_deg[frame]:.6f}",
            pitch_deg=f"{traversal.pitch_deg[frame]:.6f}",
            roll_deg=f"{traversal.roll_deg[frame]:.6f}",
            fx=f"{K[0, 0]:.6f}",
            fy=f"{K[1, 1]:.6f}",
            cx=f"{K[0, 2]:.6f}",
            cy=f"{K[1, 2]:.6f}",
        )
        R = traversal.rotations[frame]
        row.update({f"r{i}{j}": f"{R[i, j]:.9f}" for i in range(3) for j in range(3)})
        rows.append(row)
    return rows


def write_traversal_images(folder: Path, images: list[np.ndarray], width: int) -> list[str]:
    """Write RGB frames as ``<folder>/<frame:0width>.png``; returns ``<folder name>/<file>``
    names (relative to the folder's parent, the image root)."""
    folder.mkdir(parents=True, exist_ok=True)
    names = []
    for frame, image in enumerate(images):
        name = f"{frame:0{width}d}.png"
        cv2.imwrite(str(folder / name), cv2.cvtColor(image, cv2.COLOR_RGB2BGR))
        names.append(f"{folder.name}/{name}")
    return names


@dataclass
class Route:
    """One street with its clear reference drive and the offset query drive."""

    scene: Scene
    reference: Traversal  # traversal index 0: on the lane centre, clear
    query: Traversal  # traversal index 1: lateral, heading and along-track offsets
    K: np.ndarray
    image_size: tuple[int, int]
    seed: int

    @property
    def name_width(self) -> int:
        """Digits of the frame file names (at least 3)."""
        return max(3, len(str(len(self.reference) - 1)))

    def render_reference(self) -> list[np.ndarray]:
        return render_traversal(self.scene, self.reference, self.K, self.image_size, {}, self.seed, 0)

    def render_query(self, conditions: Mapping[str, float] | None = None) -> list[np.ndarray]:
        """Query frames under ``conditions``; each frame keeps its random stream
        whatever the strengths, so renders at different strengths differ only by
        the strength (common random numbers)."""
        return render_traversal(self.scene, self.query, self.K, self.image_size, conditions or {}, self.seed, 1)


def make_route(
    seed: int = 0,
    n_frames: int = 30,
    image_size: tuple[int, int] = (640, 480),
    spacing_m: float = 2.0,
    lateral_offset_m: float = 1.0,
    heading_offset_deg: float = 4.0,
    along_offset_m: float = 1.0,
) -> Route:
    """The scene and both drives ``generate_sample`` renders (same parameters, same result)."""
    scene = build_scene((n_frames - 1) * spacing_m + along_offset_m, seed)
    reference = make_traversal(n_frames, spacing_m, seed=seed, traversal_index=0)
    query = make_traversal(
        n_frames, spacing_m, lateral_offset_m, heading_offset_deg, along_offset_m, seed=seed, traversal_index=1
    )
    return Route(
        scene, reference, query, default_intrinsics(image_size), (int(image_size[0]), int(image_size[1])), int(seed)
    )


def generate_sample(
    out_dir: str | Path,
    seed: int = 0,
    n_frames: int = 30,
    conditions: Mapping[str, float] | None = None,
    image_size: tuple[int, int] = (640, 480),
    spacing_m: float = 2.0,
    lateral_offset_m: float = 1.0,
    heading_offset_deg: float = 4.0,
    along_offset_m: float = 1.0,
    max_distance_m: float = DEFAULT_MAX_DISTANCE_M,
    max_heading_deg: float = DEFAULT_MAX_HEADING_DEG,
    force: bool = False,
) -> dict:
    """Write a two-traversal sample: ``day/`` (reference, clear) and ``night/``
    (query, offset viewpoint, ``conditions`` - default a night change), plus
    ``poses.csv``, ``pairs.txt`` and ``generator.json``.

    Skips the work when ``generator.json`` records the same parameters and all
    outputs exist (unless ``force``).  Returns a summary dict.
    """
    out_dir = Path(out_dir)
    conditions = dict(DEFAULT_NIGHT_CONDITIONS if conditions is None else conditions)
    _validate_conditions(conditions)
    params = {
        "version": GENERATOR_VERSION,
        "seed": int(seed),
        "n_frames": int(n_frames),
        "conditions": {k: float(v) for k, v in sorted(conditions.items())},
        "image_size": [int(image_size[0]), int(image_size[1])],
        "spacing_m": float(spacing_m),
        "lateral_offset_m": float(lateral_offset_m),
        "heading_offset_deg": float(heading_offset_deg),
        "along_offset_m": float(along_offset_m),
        "max_distance_m": float(max_distance_m),
        "max_heading_deg": float(max_heading_deg),
    }
    params_path = out_dir / "generator.json"
    if not force and params_path.exists():
        recorded = json.loads(params_path.read_text())
        if recorded.get("params") == params and _outputs_exist(out_dir, n_frames):
            return recorded["summary"]

    # Invalidate first: an interrupted run must not look complete next time.
    params_path.unlink(missing_ok=True)
    for folder in ("day", "night"):
        for stale in (out_dir / folder).glob("*.png"):
            if stale.stem.isdigit():  # only this generator's frame files
                stale.unlink()
    route = make_route(seed, n_frames, image_size, spacing_m, lateral_offset_m, heading_offset_deg, along_offset_m)
    K, scene, day, night = route.K, route.scene, route.reference, route.query
    day_names = write_traversal_images(out_dir / "day", route.render_reference(), route.name_width)
    night_names = write_traversal_images(out_dir / "night", route.render_query(conditions), route.name_width)

    with open(out_dir / "poses.csv", "w", newline="", encoding="utf-8") as handle:
        writer = csv.DictWriter(handle, fieldnames=POSE_COLUMNS)
        writer.writeheader()
        writer.writerows(_pose_rows("day", day, K, day_names))
        writer.writerows(_pose_rows("night", night, K, night_names))

    pairs = select_pairs(scene, night, day, seed, max_distance_m, max_heading_deg)
    write_pairs(out_dir / "pairs.txt", [(night_names[q], day_names[r], label) for q, r, label in pairs])
    summary = {
        "n_images": 2 * n_frames,
        "n_pairs": len(pairs),
        "n_positives": int(sum(label for _, _, label in pairs)),
        "max_distance_m": float(max_distance_m),
        "max_heading_deg": float(max_heading_deg),
    }
    params_path.write_text(json.dumps({"params": params, "summary": summary}, indent=2))
    return summary


def _outputs_exist(out_dir: Path, n_frames: int) -> bool:
    width = max(3, len(str(n_frames - 1)))
    needed = [out_dir / "poses.csv", out_dir / "pairs.txt"]
    needed += [out_dir / t / f"{i:0{width}d}.png" for t in ("day", "night") for i in range(n_frames)]
    return all(p.exists() for p in needed)
