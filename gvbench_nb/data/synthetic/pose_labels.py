"""Labels from the poses: the pose rule (distance and heading), look-alike negatives, the pair
selection, and the fundamental matrix of a pair's true geometry.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from gvbench_nb.data.synthetic import camera_paths, street


def heading_difference_deg(heading_a: np.ndarray, heading_b: np.ndarray) -> np.ndarray:
    """Absolute heading difference wrapped to [0, 180] degrees."""
    diff = np.abs(np.asarray(heading_a, dtype=np.float64) - np.asarray(heading_b, dtype=np.float64)) % 360.0
    return np.minimum(diff, 360.0 - diff)


def pose_rule_labels(
    query_positions: np.ndarray,
    query_headings_deg: np.ndarray,
    reference_positions: np.ndarray,
    reference_headings_deg: np.ndarray,
    max_distance_m: float = street.DEFAULT_MAX_DISTANCE_M,
    max_heading_deg: float = street.DEFAULT_MAX_HEADING_DEG,
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


def _alias_reference_position(scene: street.Scene, query_x: float, look_ahead_m: float = 15.0) -> float | None:
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
    scene: street.Scene,
    query: camera_paths.Traversal,
    reference: camera_paths.Traversal,
    max_distance_m: float = street.DEFAULT_MAX_DISTANCE_M,
    max_heading_deg: float = street.DEFAULT_MAX_HEADING_DEG,
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
    headings_q = camera_paths.heading_from_rotation(query.rotations)
    headings_r = camera_paths.heading_from_rotation(reference.rotations)
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
    scene: street.Scene,
    query: camera_paths.Traversal,
    reference: camera_paths.Traversal,
    seed: int = 0,
    max_distance_m: float = street.DEFAULT_MAX_DISTANCE_M,
    max_heading_deg: float = street.DEFAULT_MAX_HEADING_DEG,
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
        camera_paths.heading_from_rotation(query.rotations),
        reference.positions,
        camera_paths.heading_from_rotation(reference.rotations),
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
