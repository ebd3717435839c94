"""A route on disk (the drives' images, poses and labelled pair file) and the embedded ``sample``."""

from __future__ import annotations

import csv
import json
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from gvbench_nb.data.sequences import write_pairs
from gvbench_nb.data.synthetic import poses, render
from gvbench_nb.data.synthetic.street import DEFAULT_MAX_DISTANCE_M, DEFAULT_MAX_HEADING_DEG, Scene, build_scene

GENERATOR_VERSION = 1
# Frame spacing and the query drive's offsets from the reference drive (generator.json records them).
DRIVE = {"spacing_m": 2.0, "lateral_offset_m": 1.0, "heading_offset_deg": 4.0, "along_offset_m": 1.0}
THRESHOLDS = {"max_distance_m": DEFAULT_MAX_DISTANCE_M, "max_heading_deg": DEFAULT_MAX_HEADING_DEG}
POSE_COLUMNS = "traversal frame image x y z yaw_deg pitch_deg roll_deg fx fy cx cy".split()  # noqa: SIM905
POSE_COLUMNS += [f"r{i}{j}" for i in range(3) for j in range(3)]


def _name_width(n_frames: int) -> int:
    """Digits of the frame file names (at least 3)."""
    return max(3, len(str(n_frames - 1)))


def write_traversal_images(folder: Path, images: list[np.ndarray], width: int) -> list[str]:
    """Write RGB frames as ``<folder>/<frame:0width>.png``; returns their names relative to the
    folder's parent (the image root)."""
    folder.mkdir(parents=True, exist_ok=True)
    names = [f"{frame:0{width}d}.png" for frame in range(len(images))]
    for name, image in zip(names, images):
        cv2.imwrite(str(folder / name), cv2.cvtColor(image, cv2.COLOR_RGB2BGR))
    return [f"{folder.name}/{name}" for name in names]


@dataclass
class Route:
    """One street with its clear reference drive and the offset query drive."""

    scene: Scene
    reference: poses.Traversal  # traversal index 0: on the lane centre, clear
    query: poses.Traversal  # traversal index 1: lateral, heading and along-track offsets
    K: np.ndarray
    image_size: tuple[int, int]
    seed: int

    @property
    def name_width(self) -> int:
        return _name_width(len(self.reference))

    def render_reference(self) -> list[np.ndarray]:
        return render.render_traversal(self.scene, self.reference, self.K, self.image_size, {}, self.seed, 0)

    def render_query(self, conditions: Mapping[str, float] | None = None) -> list[np.ndarray]:
        """Query frames under ``conditions``; a frame's random stream does not depend on the
        strengths, so renders at different strengths differ only by the strength."""
        return render.render_traversal(self.scene, self.query, self.K, self.image_size, conditions or {}, self.seed, 1)


def make_route(seed: int = 0, n_frames: int = 30, image_size: tuple[int, int] = (640, 480)) -> Route:
    """The scene and both drives ``generate_sample`` renders (same parameters, same result)."""
    scene = build_scene((n_frames - 1) * DRIVE["spacing_m"] + DRIVE["along_offset_m"], seed)
    reference = poses.make_traversal(n_frames, DRIVE["spacing_m"], seed=seed, traversal_index=0)
    query = poses.make_traversal(n_frames, **DRIVE, seed=seed, traversal_index=1)
    size = (int(image_size[0]), int(image_size[1]))
    return Route(scene, reference, query, poses.default_intrinsics(image_size), size, int(seed))


def _pose_rows(name: str, traversal: poses.Traversal, K: np.ndarray, image_names: list[str]) -> list[list]:
    rows = []
    for frame, image_name in enumerate(image_names):
        angles = (traversal.yaw_deg[frame], traversal.pitch_deg[frame], traversal.roll_deg[frame])
        values = [*traversal.positions[frame], *angles, K[0, 0], K[1, 1], K[0, 2], K[1, 2]]
        rotation = [f"{r:.9f}" for r in traversal.rotations[frame].ravel()]
        rows.append([name, frame, image_name, *(f"{v:.6f}" for v in values), *rotation])
    return rows


GENERATOR_FILE = "generator.json"  # beside a rendered route's images: what tells a synthetic sequence


def generate_sample(
    out_dir: str | Path,
    seed: int = 0,
    n_frames: int = 30,
    conditions: Mapping[str, float] | None = None,
    image_size: tuple[int, int] = (640, 480),
) -> dict:
    """Write ``day/`` (reference, clear), ``night/`` (query, offset, ``conditions``: a night by
    default), ``poses.csv``, ``pairs.txt`` and ``generator.json``; returns a summary. Skipped when
    ``generator.json`` records the same parameters and every output exists."""
    out_dir = Path(out_dir)
    conditions = dict(render.DEFAULT_NIGHT_CONDITIONS if conditions is None else conditions)
    render.validate_conditions(conditions)
    params = {
        "version": GENERATOR_VERSION,
        "seed": int(seed),
        "n_frames": int(n_frames),
        "conditions": {k: float(v) for k, v in sorted(conditions.items())},
        "image_size": [int(image_size[0]), int(image_size[1])],
        **DRIVE,
        **THRESHOLDS,
    }
    params_path = out_dir / GENERATOR_FILE
    width = _name_width(n_frames)
    frames = [out_dir / t / f"{i:0{width}d}.png" for t in ("day", "night") for i in range(n_frames)]
    if params_path.exists() and all(p.exists() for p in [out_dir / "poses.csv", out_dir / "pairs.txt", *frames]):
        recorded = json.loads(params_path.read_text())
        if recorded.get("params") == params:
            return recorded["summary"]

    # Invalidate first: an interrupted run must not look complete next time.
    params_path.unlink(missing_ok=True)
    for stale in [*(out_dir / "day").glob("*.png"), *(out_dir / "night").glob("*.png")]:
        if stale.stem.isdigit():  # only this generator's frame files
            stale.unlink()
    route = make_route(seed, n_frames, image_size)
    day_names = write_traversal_images(out_dir / "day", route.render_reference(), width)
    night_names = write_traversal_images(out_dir / "night", route.render_query(conditions), width)
    with open(out_dir / "poses.csv", "w", newline="", encoding="utf-8") as handle:
        writer = csv.writer(handle)
        writer.writerow(POSE_COLUMNS)
        writer.writerows(_pose_rows("day", route.reference, route.K, day_names))
        writer.writerows(_pose_rows("night", route.query, route.K, night_names))

    pairs = poses.select_pairs(route.scene, route.query, route.reference, seed)
    write_pairs(out_dir / "pairs.txt", [(night_names[q], day_names[r], label) for q, r, label in pairs])
    n_positives = int(sum(label for _, _, label in pairs))
    summary = {"n_images": 2 * n_frames, "n_pairs": len(pairs), "n_positives": n_positives, **THRESHOLDS}
    params_path.write_text(json.dumps({"params": params, "summary": summary}, indent=2))
    return summary
