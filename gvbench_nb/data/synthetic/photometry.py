"""Photometric conditions of a rendered frame (illumination, season, weather), each a strength in [0, 1]."""

from __future__ import annotations

import math
from collections.abc import Mapping

import cv2
import numpy as np

CONDITIONS: tuple[str, ...] = ("illumination", "season", "weather")
DEFAULT_NIGHT_CONDITIONS: dict[str, float] = {"illumination": 0.7}


def validate_conditions(conditions: Mapping[str, float]) -> dict[str, float]:
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
    """Light pools on surfaces near each lamp and the lamps' glare, (H, W) each (smooth, so
    computed at 1/``downscale`` resolution)."""
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


def apply_conditions(
    image: np.ndarray,
    depth: np.ndarray,
    normals: np.ndarray,
    conditions: Mapping[str, float],
    rng: np.random.Generator,
    *,
    light_points: np.ndarray,
) -> np.ndarray:
    """Apply condition strengths in physical order: surfaces (season), the medium (weather), then
    the camera (illumination: exposure, gain noise, glare). Zero strengths leave the image as it is;
    ``light_points`` (M, 4: u, v, depth, pool radius in px) places the night lamps."""
    strengths = validate_conditions(conditions)
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
