"""Rendering a frame: each rectangle's inverse depth is affine in pixel (u, v), so a z-buffer pass
costs a few array operations over its screen box and texturing is one ``cv2.remap`` per mip level.
"""

from __future__ import annotations

import math
import os
from collections.abc import Mapping
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import cv2
import numpy as np

from gvbench_nb.data.synthetic import photometry
from gvbench_nb.data.synthetic.poses import Traversal
from gvbench_nb.data.synthetic.street import Scene, texture_pyramid

NEAR_PLANE_M = 0.1


@dataclass
class RenderedFrame:
    """Clear render plus the per-pixel geometry conditions need."""

    image: np.ndarray  # (H, W, 3) uint8 RGB
    depth: np.ndarray  # (H, W) float32 camera z-depth, inf for sky
    normals: np.ndarray  # (H, W, 3) float32 world-frame unit normals, 0 for sky
    light_points: np.ndarray  # (M, 4) visible lamps: u, v, depth, pool radius px


def _screen_box(corners_cam: np.ndarray, K: np.ndarray, width: int, height: int):
    """Integer pixel box (c0, r0, c1, r1) covering the rectangle clipped to the near plane
    (Sutherland-Hodgman), or None."""
    clipped = []
    for p, q in zip(corners_cam, np.roll(corners_cam, -1, axis=0)):
        if p[2] >= NEAR_PLANE_M:
            clipped.append(p)
        if (p[2] >= NEAR_PLANE_M) != (q[2] >= NEAR_PLANE_M):
            clipped.append(p + (NEAR_PLANE_M - p[2]) / (q[2] - p[2]) * (q - p))
    if len(clipped) < 3:
        return None
    projected = (K @ np.array(clipped).T).T
    uv = projected[:, :2] / projected[:, 2:3]
    c0, r0 = max(int(math.floor(uv[:, 0].min())), 0), max(int(math.floor(uv[:, 1].min())), 0)
    c1, r1 = min(int(math.ceil(uv[:, 0].max())) + 1, width), min(int(math.ceil(uv[:, 1].max())) + 1, height)
    return None if c0 >= c1 or r0 >= r1 else (c0, r0, c1, r1)


def _remap_flat(texture: np.ndarray, map_x: np.ndarray, map_y: np.ndarray) -> np.ndarray:
    """cv2.remap for a flat list of coordinates (remap needs < 32767 rows)."""
    n, cols = len(map_x), 1024
    rows = -(-n // cols)
    maps = np.zeros((2, rows * cols), dtype=np.float32)
    maps[0, :n], maps[1, :n] = map_x, map_y
    maps = maps.reshape(2, rows, cols)
    out = cv2.remap(texture, maps[0], maps[1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_WRAP)
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
    """A rectangle as functions of pixel (u, v): for ray r = K^-1 [u, v, 1] the inverse depth is
    q = (n . r) / d and the in-plane coordinate a = (u_hat . r) / q - u_hat . P0 (b alike)."""

    q_coef: np.ndarray  # (3,) float32
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


def _planes_in_camera(scene: Scene, rotation: np.ndarray, position: np.ndarray, K_inv: np.ndarray):
    """Indices, camera-frame corners and plane functions of the rectangles facing the camera."""
    R_wc = rotation.T
    origin = (scene.origin - position) @ R_wc.T
    edge_u, edge_v = scene.edge_u @ R_wc.T, scene.edge_v @ R_wc.T
    u_length, v_length = np.linalg.norm(edge_u, axis=1), np.linalg.norm(edge_v, axis=1)
    u_hat, v_hat = edge_u / u_length[:, None], edge_v / v_length[:, None]
    normal = np.cross(u_hat, v_hat)
    plane_offset = np.einsum("ij,ij->i", normal, origin)
    front = np.flatnonzero(plane_offset < -1e-6)  # one-sided: the camera is on the normal's side
    corners = np.stack([origin, origin + edge_u, origin + edge_u + edge_v, origin + edge_v], axis=1)
    planes = [
        _PlaneInCamera(
            ((normal[i] @ K_inv) / plane_offset[i]).astype(np.float32),
            (u_hat[i] @ K_inv).astype(np.float32),
            (v_hat[i] @ K_inv).astype(np.float32),
            float(u_hat[i] @ origin[i]),
            float(v_hat[i] @ origin[i]),
            float(u_length[i]),
            float(v_length[i]),
            float(plane_offset[i]),
        )
        for i in front
    ]
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
        box = _screen_box(corners[k], K, width, height)
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
    ray_norm = np.sqrt(
        ((cols[None, :] - K[0, 2]) / K[0, 0]) ** 2 + ((rows[:, None] - K[1, 2]) / K[1, 1]) ** 2 + 1.0
    ).ravel()
    world_normal = scene.normal.astype(np.float32)
    for k in (np.flatnonzero(counts) - 1).tolist():  # -1 is the sky
        pixels = order[bounds[k + 1] : bounds[k + 2]]
        rr, cc = np.divmod(pixels, width)
        if k < 0:
            pixel_h = np.stack([cc, rr, np.ones_like(cc)], axis=1).astype(np.float32)
            image[pixels] = _sky_colour(pixel_h @ (rotation @ K_inv).T.astype(np.float32))
            continue
        i = front[k]
        uv = (cc.astype(np.float32), rr.astype(np.float32))
        image[pixels] = _texture_colours(scene, i, planes[k], *uv, ray_norm[pixels], float(K[0, 0]))
        normals[pixels] = world_normal[i]

    # Mild optical blur: real lenses are not perfectly sharp, and it hides unsupersampled edges.
    image = cv2.GaussianBlur(image.reshape(height, width, 3), (0, 0), 0.6)
    depth = np.where(inv_depth > 0, 1.0 / np.maximum(inv_depth, 1e-12), np.inf).astype(np.float32)
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
    pyramid = texture_pyramid(scene.texture[i])
    tex_h, tex_w = pyramid[0].shape[:2]
    texels_per_metre = np.float32(tex_w / scene.metres_per_texture[i])
    # Mip level from a pixel's texel footprint; obliquity counts only half (sqrt), so grazing
    # surfaces blur less than isotropic mipmaps would.
    cos_incidence = np.abs(q * np.float32(plane.plane_offset) / ray_norm)
    footprint = texels_per_metre / (q * focal) / np.sqrt(np.maximum(cos_incidence, 0.05))
    level = np.clip(np.rint(np.log2(np.maximum(footprint, 1e-6))), 0, len(pyramid) - 1).astype(np.int8)
    # Wrap into the base texture before scaling to a level: every level tiles with its own size.
    tex_x = np.mod(a * texels_per_metre + np.float32(scene.texture_offset[i, 0] * tex_w), tex_w)
    tex_y = np.mod(np.float32(scene.texture_offset[i, 1] * tex_w) - b * texels_per_metre, tex_h)
    colours = np.empty((len(u), 3), dtype=np.float32)
    for lv in range(int(level.min()), int(level.max()) + 1):
        sel = level == lv
        if sel.any():
            tex = pyramid[lv]
            scale_x, scale_y = np.float32(tex.shape[1] / tex_w), np.float32(tex.shape[0] / tex_h)
            colours[sel] = _remap_flat(tex, tex_x[sel] * scale_x, tex_y[sel] * scale_y)
    return colours * scene.tint[i]


def _visible_lamps(
    lamps: np.ndarray, rotation: np.ndarray, position: np.ndarray, K: np.ndarray, depth: np.ndarray
) -> np.ndarray:
    """Lamp heads in view and not hidden behind a surface: u, v, depth, light-pool radius (px)."""
    height, width = depth.shape
    cam = (lamps - position) @ rotation
    cam = cam[cam[:, 2] > 1.0]
    uv = (cam @ K.T)[:, :2] / cam[:, 2:3]
    inside = (uv[:, 0] >= 0) & (uv[:, 0] < width) & (uv[:, 1] >= 0) & (uv[:, 1] < height)
    cam, uv = cam[inside], uv[inside]
    unoccluded = cam[:, 2] <= depth[uv[:, 1].astype(int), uv[:, 0].astype(int)] + 0.5
    return np.column_stack([uv, cam[:, 2], K[0, 0] * 4.0 / cam[:, 2]])[unoccluded]  # ~4 m light pool


def frame_rng(seed: int, traversal_index: int, frame_index: int) -> np.random.Generator:
    """Independent, reproducible random stream per rendered frame."""
    return np.random.default_rng([seed, 3, traversal_index, frame_index])


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
    """Every frame of a traversal under ``conditions`` (RGB uint8), on ``workers`` threads (numpy
    and OpenCV release the GIL); each frame has its own random stream, so workers change nothing."""
    conditions = dict(conditions or {})
    photometry.validate_conditions(conditions)

    def render(frame: int) -> np.ndarray:
        clear = render_frame(scene, traversal.rotations[frame], traversal.positions[frame], K, image_size)
        rng = frame_rng(seed, traversal_index, frame)
        return photometry.apply_conditions(
            clear.image, clear.depth, clear.normals, conditions, rng, light_points=clear.light_points
        )

    with ThreadPoolExecutor(max_workers=workers or min(4, os.cpu_count() or 1)) as pool:
        return list(pool.map(render, range(len(traversal))))
