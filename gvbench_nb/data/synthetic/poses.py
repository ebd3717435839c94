"""Camera poses (OpenCV camera frame; camera-to-world rotation R and centre t) and the labels they
give: the pose rule, look-alike negatives and the pair selection."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from gvbench_nb.data.retrieval import heading_difference_deg
from gvbench_nb.data.synthetic.street import DEFAULT_MAX_DISTANCE_M, DEFAULT_MAX_HEADING_DEG, Scene

# Per query frame: true pairs, near negatives (hard: they still overlap) and far negatives.
N_POSITIVES, N_NEAR_NEGATIVES, N_FAR_NEGATIVES = 3, 2, 2
# Wider than the 15 m select_pairs uses: on the 30-frame seed-0 route, query frame 0 stands 15.4 m
# before the block and its look-alike reference scores 147 SIFT inliers, more than most true pairs.
LOOK_ALIKE_LOOK_AHEAD_M = 25.0


def default_intrinsics(image_size: tuple[int, int] = (640, 480)) -> np.ndarray:
    """Pinhole K with a ~64 deg horizontal field of view for (width, height)."""
    width, height = image_size
    focal = 0.8 * width
    return np.array([[focal, 0.0, (width - 1) / 2.0], [0.0, focal, (height - 1) / 2.0], [0.0, 0.0, 1.0]])


def camera_rotation(yaw_deg: float, pitch_deg: float = 0.0, roll_deg: float = 0.0) -> np.ndarray:
    """Camera-to-world rotation for a heading (about world Z, 0 = +X), pitch (up) and roll."""
    yaw, pitch, roll = np.deg2rad([yaw_deg, pitch_deg, roll_deg])
    # Camera axes at yaw 0: x_cam -> -Y (right), y_cam -> -Z (down), z_cam -> +X.
    base = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
    cz, cp, cr = (math.cos(angle) for angle in (yaw, pitch, roll))
    sz, sp, sr = (math.sin(angle) for angle in (yaw, pitch, roll))
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

    positions: np.ndarray  # (N, 3) camera centres, world frame (X along the street, Z up; metres)
    rotations: np.ndarray  # (N, 3, 3) camera-to-world
    yaw_deg: np.ndarray
    pitch_deg: np.ndarray
    roll_deg: np.ndarray

    def __len__(self) -> int:
        return len(self.positions)


def make_traversal(
    n_frames: int,
    spacing_m: float = 2.0,
    lateral_offset_m: float = 0.0,
    heading_offset_deg: float = 0.0,
    along_offset_m: float = 0.0,
    seed: int = 0,
    traversal_index: int = 0,
) -> Traversal:
    """Forward drive along +X at 1.7 m with a per-traversal offset and smooth pose jitter (a driver
    does not zig-zag frame to frame)."""
    rng = np.random.default_rng([seed, 2, traversal_index])
    kernel = np.exp(-0.5 * (np.arange(-8, 9) / 4.0) ** 2)
    kernel /= np.linalg.norm(kernel)
    jitter = lambda amplitude: amplitude * np.convolve(rng.normal(size=n_frames + 16), kernel, "same")[8 : 8 + n_frames]
    x = along_offset_m + spacing_m * np.arange(n_frames)
    y = lateral_offset_m + jitter(0.15)
    z = 1.7 + jitter(0.03)
    yaw = heading_offset_deg + jitter(1.5)
    pitch, roll = jitter(0.6), jitter(0.4)
    rotations = np.stack([camera_rotation(a, b, c) for a, b, c in zip(yaw, pitch, roll)])
    return Traversal(np.stack([x, y, z], axis=1), rotations, yaw, pitch, roll)


def pose_rule_labels(
    query_positions: np.ndarray,
    query_headings_deg: np.ndarray,
    reference_positions: np.ndarray,
    reference_headings_deg: np.ndarray,
    max_distance_m: float = DEFAULT_MAX_DISTANCE_M,
    max_heading_deg: float = DEFAULT_MAX_HEADING_DEG,
) -> np.ndarray:
    """GV-Bench pose rule: (Q, R) bool, True where the camera centres are within ``max_distance_m``
    (3-D) and the headings within ``max_heading_deg``."""
    query_positions = np.atleast_2d(np.asarray(query_positions, dtype=np.float64))
    reference_positions = np.atleast_2d(np.asarray(reference_positions, dtype=np.float64))
    distance = np.linalg.norm(query_positions[:, None, :] - reference_positions[None, :, :], axis=2)
    heading = heading_difference_deg(
        np.atleast_1d(query_headings_deg)[:, None], np.atleast_1d(reference_headings_deg)[None, :]
    )
    return (distance <= max_distance_m) & (heading <= max_heading_deg)


def _alias_reference_position(scene: Scene, query_x: float, look_ahead_m: float = 15.0) -> float | None:
    """Where the look-alike of what the query sees would be seen from, if the query has a repeated
    façade block within ``look_ahead_m`` ahead."""
    for source_x, copy_x, length in scene.alias_blocks:
        shift = copy_x - source_x
        if source_x - look_ahead_m <= query_x <= source_x + 0.5 * length:
            return query_x + shift
        if copy_x - look_ahead_m <= query_x <= copy_x + 0.5 * length:
            return query_x - shift
    return None


def look_alike_labels(
    scene: Scene, query: Traversal, reference: Traversal, look_ahead_m: float = LOOK_ALIKE_LOOK_AHEAD_M
) -> np.ndarray:
    """(Q, R) bool: pairs false by the pose rule but true from the query's look-alike position (its
    position shifted by the repeated block's offset), so both images show the same façades."""
    headings_q, headings_r = heading_from_rotation(query.rotations), heading_from_rotation(reference.rotations)
    true_pairs = pose_rule_labels(query.positions, headings_q, reference.positions, headings_r)
    look_alike = np.zeros_like(true_pairs)
    for qi, position in enumerate(query.positions):
        alias_x = _alias_reference_position(scene, float(position[0]), look_ahead_m)
        if alias_x is None:
            continue
        shifted = position.copy()
        shifted[0] = alias_x
        look_alike[qi] = pose_rule_labels(shifted, headings_q[qi : qi + 1], reference.positions, headings_r)[0]
    return look_alike & ~true_pairs


def select_pairs(scene: Scene, query: Traversal, reference: Traversal, seed: int = 0) -> list[tuple[int, int, int]]:
    """(query, reference, label) per query frame: the nearest true reference and random further
    ones, near and far negatives, and the look-alike when the query sees a repeated block
    (otherwise one more far negative). All choices come from ``seed``."""
    rng = np.random.default_rng([seed, 4])
    headings_q, headings_r = heading_from_rotation(query.rotations), heading_from_rotation(reference.rotations)
    labels = pose_rule_labels(query.positions, headings_q, reference.positions, headings_r)
    distance = np.linalg.norm(query.positions[:, None] - reference.positions[None], axis=2)
    pairs: list[tuple[int, int, int]] = []
    for qi in range(len(query)):
        order = np.argsort(distance[qi], kind="stable")
        positives = [r for r in order if labels[qi, r]]
        negatives = [r for r in order if not labels[qi, r]]
        near = [r for r in negatives if distance[qi, r] <= 2.5 * DEFAULT_MAX_DISTANCE_M]
        far = [r for r in negatives if distance[qi, r] > 2.5 * DEFAULT_MAX_DISTANCE_M]
        chosen: list[int] = positives[:1]
        chosen += _pick(rng, positives[1:], N_POSITIVES - len(chosen))
        chosen += _pick(rng, near, N_NEAR_NEGATIVES)
        alias_x = _alias_reference_position(scene, float(query.positions[qi, 0]))
        alias_ref = None
        if alias_x is not None:
            candidate = int(np.argmin(np.abs(reference.positions[:, 0] - alias_x)))
            if not labels[qi, candidate] and candidate not in chosen:
                alias_ref = candidate
        chosen += _pick(rng, [r for r in far if r != alias_ref], N_FAR_NEGATIVES + (alias_ref is None))
        if alias_ref is not None:
            chosen.append(alias_ref)
        # Short routes lack far negatives: top up with other negatives, then positives.
        target = N_POSITIVES + N_NEAR_NEGATIVES + N_FAR_NEGATIVES + 1
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
