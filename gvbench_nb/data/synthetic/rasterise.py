"""Rendering a frame: each plane mapped into the camera by its homography, clipped at the near
plane, composited by depth, then the conditions applied.
"""

from __future__ import annotations

import math
import os
from collections.abc import Mapping
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import cv2
import numpy as np

from gvbench_nb.data.synthetic import camera_paths, photometry, street


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
    scene: street.Scene, rotation: np.ndarray, position: np.ndarray, K_inv: np.ndarray
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
    scene: street.Scene,
    rotation: np.ndarray,
    position: np.ndarray,
    K: np.ndarray,
    image_size: tuple[int, int] = (640, 480),
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
    depth = np.where(inv_depth > 0, 1.0 / np.maximum(inv_depth, 1e-12), street.SKY_DEPTH).astype(np.float32)
    lights = _visible_lamps(scene.lamps, rotation, position, K, depth)
    return RenderedFrame(
        np.clip(np.rint(image), 0, 255).astype(np.uint8), depth, normals.reshape(height, width, 3), lights
    )


def _texture_colours(
    scene: street.Scene, i: int, plane: _PlaneInCamera, u: np.ndarray, v: np.ndarray, ray_norm: np.ndarray, focal: float
) -> np.ndarray:
    """Tinted texture colours of rectangle ``i`` at pixels (u, v), mip-mapped."""
    q = plane.inverse_depth(u, v)
    a, b = plane.plane_coordinates(u, v, 1.0 / q)
    pyramid = street.texture_pyramid(scene.texture[i])
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
    scene: street.Scene,
    traversal: camera_paths.Traversal,
    frame: int,
    K: np.ndarray,
    image_size: tuple[int, int],
    conditions: Mapping[str, float],
    seed: int,
    traversal_index: int,
) -> np.ndarray:
    rendered = render_frame(scene, traversal.rotations[frame], traversal.positions[frame], K, image_size)
    return photometry.apply_conditions(
        rendered.image,
        rendered.depth,
        rendered.normals,
        conditions,
        frame_rng(seed, traversal_index, frame),
        light_points=rendered.light_points,
    )


def render_traversal(
    scene: street.Scene,
    traversal: camera_paths.Traversal,
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
    photometry.validate_conditions(conditions)
    workers = workers or min(4, os.cpu_count() or 1)

    def render(frame: int) -> np.ndarray:
        return _render_with_conditions(scene, traversal, frame, K, image_size, conditions, seed, traversal_index)

    if workers <= 1:
        return [render(frame) for frame in range(len(traversal))]
    with ThreadPoolExecutor(max_workers=workers) as pool:
        return list(pool.map(render, range(len(traversal))))
