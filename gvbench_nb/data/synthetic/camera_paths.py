"""Cameras along the route: intrinsics, rotations, and a traversal's smoothly wandering poses."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


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
