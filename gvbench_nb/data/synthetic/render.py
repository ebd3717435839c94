"""Rendering a frame and its conditions. A rectangle's inverse depth is affine in pixel (u, v), so a
z-buffer pass costs a few array operations over its screen box and texturing is one ``cv2.remap``
per mip level. Conditions (illumination, season, weather) each have a strength in [0, 1]."""

from __future__ import annotations

import math
import os
from collections import namedtuple
from collections.abc import Mapping
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import cv2
import numpy as np

from gvbench_nb.data.synthetic.poses import Traversal
from gvbench_nb.data.synthetic.street import Scene, texture_pyramid

CONDITIONS: tuple[str, ...] = ("illumination", "season", "weather")
DEFAULT_NIGHT_CONDITIONS: dict[str, float] = {"illumination": 0.7}


@dataclass
class RenderedFrame:
    """Clear render plus the per-pixel geometry conditions need."""

    image: np.ndarray  # (H, W, 3) uint8 RGB
    depth: np.ndarray  # (H, W) float32 camera z-depth, inf for sky
    normals: np.ndarray  # (H, W, 3) float32 world-frame unit normals, 0 for sky
    light_points: np.ndarray  # (M, 4) visible lamps: u, v, depth, pool radius px


def validate_conditions(conditions: Mapping[str, float]) -> dict[str, float]:
    unknown = set(conditions) - set(CONDITIONS)
    if unknown:
        raise ValueError(f"unknown conditions {sorted(unknown)}; known: {CONDITIONS}")
    strengths = {name: float(conditions.get(name, 0.0)) for name in CONDITIONS}
    for name, strength in strengths.items():
        if not 0.0 <= strength <= 1.0:
            raise ValueError(f"condition {name!r} strength {strength} outside [0, 1]")
    return strengths


def _apply_season(
    image: np.ndarray, normals: np.ndarray, depth: np.ndarray, strength: float, rng: np.random.Generator
) -> np.ndarray:
    """Winter: snow on upward-facing surfaces, brown vegetation, pale overcast light."""
    up = np.clip(normals[..., 2], 0.0, 1.0)
    height, width = up.shape  # snow patchiness: a smooth random field in [0, 1]
    coarse = rng.uniform(size=(12, max(2, 12 * width // height))).astype(np.float32)
    patchiness = np.clip(cv2.resize(coarse, (width, height), interpolation=cv2.INTER_CUBIC), 0.0, 1.0)
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
    """Light pools on surfaces near each lamp and the lamps' glare, (H, W) each (smooth, so
    computed at 1/``downscale`` resolution)."""
    height, width = depth.shape
    small_depth = np.where(np.isinf(depth), 1e4, depth)[::downscale, ::downscale]
    rows, cols = np.mgrid[0 : small_depth.shape[0], 0 : small_depth.shape[1]].astype(np.float32)
    rows, cols = rows * downscale, cols * downscale
    pool, glare = np.zeros_like(small_depth), np.zeros_like(small_depth)
    for u, v, lamp_depth, radius in np.asarray(light_points, dtype=np.float32).reshape(-1, 4):
        # The pool sits below the lamp head and only on surfaces at its depth.
        distance_sq = (cols - u) ** 2 + (rows - v - 0.6 * radius) ** 2
        near_lamp = np.exp(-np.abs(small_depth - lamp_depth) / 5.0)
        pool += np.exp(-distance_sq / (2 * radius**2)) * near_lamp
        glare_sigma = 3.0 * max(2.0, 0.08 * radius)
        glare += np.exp(-((cols - u) ** 2 + (rows - v) ** 2) / (2 * glare_sigma**2))
    pool, glare = (cv2.resize(field, (width, height), interpolation=cv2.INTER_LINEAR) for field in (pool, glare))
    return pool, glare


def _apply_illumination(
    image: np.ndarray, depth: np.ndarray, strength: float, rng: np.random.Generator, light_points: np.ndarray
) -> np.ndarray:
    """Day -> night: less daylight, headlights and lamps, colour cast, gain noise."""
    height = depth.shape[0]
    linear = (image * np.float32(1 / 255.0)) ** np.float32(2.2)
    daylight = math.exp(-4.0 * strength)  # ~6 % of daylight at strength 0.7

    # Headlights of the recording vehicle light the road and near surfaces.
    finite_depth = np.where(np.isinf(depth), 1e4, depth)
    row_weight = np.exp(-((np.arange(height, dtype=np.float32)[:, None] / height - 0.85) ** 2) / 0.12)
    headlight = np.float32(strength * 0.6) * np.exp(-finite_depth / np.float32(8.0)) * row_weight
    pool, glare = _lamp_fields(depth, light_points)
    warm = np.array([1.0, 0.75, 0.45], dtype=np.float32)  # sodium-lamp orange
    # Auto-exposure raises the gain (and the noise); white balance stays set for daylight.
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

    # Shot noise grows with signal and gain, read noise with gain; reused buffers spare page faults.
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


def apply_conditions(frame: RenderedFrame, conditions: Mapping[str, float], rng: np.random.Generator) -> np.ndarray:
    """A clear frame under condition strengths (all zero: unchanged), in physical order: surfaces
    (season), the medium (weather), then the camera (illumination: exposure, gain noise, glare)."""
    strengths = validate_conditions(conditions)
    if all(s == 0.0 for s in strengths.values()):
        return frame.image.copy()
    result, depth = frame.image.astype(np.float32), frame.depth
    if strengths["season"] > 0:
        result = _apply_season(result, frame.normals, depth, strengths["season"], rng)
    if strengths["weather"] > 0:
        result = _apply_weather(result, depth, strengths["weather"], rng)
    if strengths["illumination"] > 0:
        result = _apply_illumination(np.clip(result, 0, 255), depth, strengths["illumination"], rng, frame.light_points)
    return np.clip(np.rint(result), 0, 255).astype(np.uint8)


NEAR_PLANE_M = 0.1


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
    map_rows = maps.reshape(2, rows, cols)
    out = cv2.remap(texture, map_rows[0], map_rows[1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_WRAP)
    return out.reshape(rows * cols, -1)[:n]


def _sky_colour(ray_world: np.ndarray) -> np.ndarray:
    """Smooth blue gradient by elevation (RGB float 0-255)."""
    elevation = np.clip(ray_world[..., 2] / np.linalg.norm(ray_world, axis=-1), 0.0, 1.0)
    horizon = np.array([200.0, 215.0, 230.0], dtype=np.float32)
    zenith = np.array([95.0, 140.0, 205.0], dtype=np.float32)
    weight = np.sqrt(elevation)[..., None].astype(np.float32)
    return horizon * (1 - weight) + zenith * weight


# A facing rectangle as functions of pixel (u, v): for ray r = K^-1 [u, v, 1] the inverse depth is
# q = (n . r) / d (d = n . P0 < 0: camera on the visible side), the in-plane a = (u_hat . r) / q - u_hat . P0.
_Plane = namedtuple("_Plane", "q_coef a_coef b_coef a_offset b_offset u_length v_length plane_offset")


def _affine(coef: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    return coef[0] * u + coef[1] * v + coef[2]


def _plane_coordinates(plane: _Plane, u: np.ndarray, v: np.ndarray, inv_q: np.ndarray):
    return _affine(plane.a_coef, u, v) * inv_q - plane.a_offset, _affine(plane.b_coef, u, v) * inv_q - plane.b_offset


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
    planes = []
    for i in front:
        q_coef = ((normal[i] @ K_inv) / plane_offset[i]).astype(np.float32)
        a_coef, b_coef = ((hat[i] @ K_inv).astype(np.float32) for hat in (u_hat, v_hat))
        offsets = (float(u_hat[i] @ origin[i]), float(v_hat[i] @ origin[i]), float(u_length[i]), float(v_length[i]))
        planes.append(_Plane(q_coef, a_coef, b_coef, *offsets, float(plane_offset[i])))
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
    rect_id = np.full((height, width), -1, dtype=np.int16 if len(scene.texture) < 32000 else np.int32)
    cols = np.arange(width, dtype=np.float32)
    rows = np.arange(height, dtype=np.float32)
    for k, plane in enumerate(planes):
        box = _screen_box(corners[k], K, width, height)
        if box is None:
            continue
        c0, r0, c1, r1 = box
        uu, vv = cols[None, c0:c1], rows[r0:r1, None]
        q = _affine(plane.q_coef, uu, vv)
        zbuf = inv_depth[r0:r1, c0:c1]
        hit = q > zbuf
        if not hit.any():
            continue
        a, b = _plane_coordinates(plane, uu, vv, 1.0 / np.maximum(q, 1e-9))
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
    scene: Scene, i: int, plane: _Plane, u: np.ndarray, v: np.ndarray, ray_norm: np.ndarray, focal: float
) -> np.ndarray:
    """Tinted texture colours of rectangle ``i`` at pixels (u, v), mip-mapped."""
    q = _affine(plane.q_coef, u, v)
    a, b = _plane_coordinates(plane, u, v, 1.0 / q)
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
    validate_conditions(conditions)

    def render(frame: int) -> np.ndarray:
        clear = render_frame(scene, traversal.rotations[frame], traversal.positions[frame], K, image_size)
        return apply_conditions(clear, conditions, np.random.default_rng([seed, 3, traversal_index, frame]))

    with ThreadPoolExecutor(max_workers=workers or min(4, os.cpu_count() or 1)) as pool:
        return list(pool.map(render, range(len(traversal))))
