"""Deterministic synthetic street route textured with scikit-image's photographs, driven twice with
exact poses, conditions applied per drive, pairs labelled by the GV-Bench pose rule. World frame:
X along the street, Y left, Z up (metres)."""

from gvbench_nb.data.synthetic.poses import LOOK_ALIKE_LOOK_AHEAD_M, look_alike_labels, select_pairs
from gvbench_nb.data.synthetic.render import CONDITIONS, render_traversal
from gvbench_nb.data.synthetic.route_files import (
    GENERATOR_VERSION,
    Route,
    generate_sample,
    make_route,
    write_traversal_images,
)
from gvbench_nb.data.synthetic.street import DEFAULT_MAX_DISTANCE_M, DEFAULT_MAX_HEADING_DEG

__all__ = [
    "CONDITIONS",
    "DEFAULT_MAX_DISTANCE_M",
    "DEFAULT_MAX_HEADING_DEG",
    "GENERATOR_VERSION",
    "LOOK_ALIKE_LOOK_AHEAD_M",
    "Route",
    "generate_sample",
    "look_alike_labels",
    "make_route",
    "render_traversal",
    "select_pairs",
    "write_traversal_images",
]
