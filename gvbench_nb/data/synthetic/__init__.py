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

from gvbench_nb.data.synthetic.camera_paths import (
    Traversal,
    camera_rotation,
    default_intrinsics,
    heading_from_rotation,
    make_traversal,
)
from gvbench_nb.data.synthetic.photometry import CONDITIONS, DEFAULT_NIGHT_CONDITIONS, apply_conditions
from gvbench_nb.data.synthetic.pose_labels import (
    LOOK_ALIKE_LOOK_AHEAD_M,
    fundamental_from_poses,
    heading_difference_deg,
    look_alike_labels,
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
    "GENERATOR_VERSION",
    "LOOK_ALIKE_LOOK_AHEAD_M",
    "frame_rng",
]
