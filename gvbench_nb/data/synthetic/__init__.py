"""Deterministic synthetic street route for geometric-verification studies: façades, side streets,
ground and street furniture textured with scikit-image's photographs, driven twice with exact 6-DoF
poses, conditions (illumination, season, weather) applied per drive with a strength in [0, 1], and
pairs labelled by the GV-Bench pose rule.

World frame: X along the street, Y left, Z up (metres). Camera frame (OpenCV): x right, y down,
z forward; a pose is the camera-to-world rotation R and the centre t (X_world = R @ X_cam + t).
"""

from gvbench_nb.data.synthetic.photometry import CONDITIONS, DEFAULT_NIGHT_CONDITIONS, apply_conditions
from gvbench_nb.data.synthetic.poses import (
    LOOK_ALIKE_LOOK_AHEAD_M,
    Traversal,
    camera_rotation,
    default_intrinsics,
    fundamental_from_poses,
    heading_difference_deg,
    heading_from_rotation,
    look_alike_labels,
    make_traversal,
    pose_rule_labels,
    select_pairs,
)
from gvbench_nb.data.synthetic.rasterise import RenderedFrame, frame_rng, render_frame, render_traversal
from gvbench_nb.data.synthetic.route_files import (
    GENERATOR_VERSION,
    Route,
    generate_sample,
    make_route,
    write_traversal_images,
)
from gvbench_nb.data.synthetic.street import DEFAULT_MAX_DISTANCE_M, DEFAULT_MAX_HEADING_DEG, Scene, build_scene

__all__ = [
    "CONDITIONS",
    "DEFAULT_MAX_DISTANCE_M",
    "DEFAULT_MAX_HEADING_DEG",
    "DEFAULT_NIGHT_CONDITIONS",
    "GENERATOR_VERSION",
    "LOOK_ALIKE_LOOK_AHEAD_M",
    "RenderedFrame",
    "Route",
    "Scene",
    "Traversal",
    "apply_conditions",
    "build_scene",
    "camera_rotation",
    "default_intrinsics",
    "frame_rng",
    "fundamental_from_poses",
    "generate_sample",
    "heading_difference_deg",
    "heading_from_rotation",
    "look_alike_labels",
    "make_route",
    "make_traversal",
    "pose_rule_labels",
    "render_frame",
    "render_traversal",
    "select_pairs",
    "write_traversal_images",
]
