"""A route on disk: the traversals' images, their poses and the labelled pair file, and the
``sample`` sequence the package embeds.
"""

from __future__ import annotations

import csv
import json
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from gvbench_nb.data.sequences import write_pairs
from gvbench_nb.data.synthetic import camera_paths, photometry, pose_labels, rasterise, street

GENERATOR_VERSION = 1


POSE_COLUMNS = [
    "traversal",
    "frame",
    "image",
    "x",
    "y",
    "z",
    "yaw_deg",
    "pitch_deg",
    "roll_deg",
    "fx",
    "fy",
    "cx",
    "cy",
] + [f"r{i}{j}" for i in range(3) for j in range(3)]


def _pose_rows(name: str, traversal: camera_paths.Traversal, K: np.ndarray, image_names: list[str]) -> list[dict]:
    rows = []
    for frame, image_name in enumerate(image_names):
        row = {"traversal": name, "frame": frame, "image": image_name}
        row.update(zip("xyz", (f"{v:.6f}" for v in traversal.positions[frame])))
        row.update(
            yaw_deg=f"{traversal.yaw_deg[frame]:.6f}",
            pitch_deg=f"{traversal.pitch_deg[frame]:.6f}",
            roll_deg=f"{traversal.roll_deg[frame]:.6f}",
            fx=f"{K[0, 0]:.6f}",
            fy=f"{K[1, 1]:.6f}",
            cx=f"{K[0, 2]:.6f}",
            cy=f"{K[1, 2]:.6f}",
        )
        R = traversal.rotations[frame]
        row.update({f"r{i}{j}": f"{R[i, j]:.9f}" for i in range(3) for j in range(3)})
        rows.append(row)
    return rows


def write_traversal_images(folder: Path, images: list[np.ndarray], width: int) -> list[str]:
    """Write RGB frames as ``<folder>/<frame:0width>.png``; returns ``<folder name>/<file>``
    names (relative to the folder's parent, the image root)."""
    folder.mkdir(parents=True, exist_ok=True)
    names = []
    for frame, image in enumerate(images):
        name = f"{frame:0{width}d}.png"
        cv2.imwrite(str(folder / name), cv2.cvtColor(image, cv2.COLOR_RGB2BGR))
        names.append(f"{folder.name}/{name}")
    return names


@dataclass
class Route:
    """One street with its clear reference drive and the offset query drive."""

    scene: street.Scene
    reference: camera_paths.Traversal  # traversal index 0: on the lane centre, clear
    query: camera_paths.Traversal  # traversal index 1: lateral, heading and along-track offsets
    K: np.ndarray
    image_size: tuple[int, int]
    seed: int

    @property
    def name_width(self) -> int:
        """Digits of the frame file names (at least 3)."""
        return max(3, len(str(len(self.reference) - 1)))

    def render_reference(self) -> list[np.ndarray]:
        return rasterise.render_traversal(self.scene, self.reference, self.K, self.image_size, {}, self.seed, 0)

    def render_query(self, conditions: Mapping[str, float] | None = None) -> list[np.ndarray]:
        """Query frames under ``conditions``; each frame keeps its random stream
        whatever the strengths, so renders at different strengths differ only by
        the strength (common random numbers)."""
        return rasterise.render_traversal(
            self.scene, self.query, self.K, self.image_size, conditions or {}, self.seed, 1
        )


def make_route(
    seed: int = 0,
    n_frames: int = 30,
    image_size: tuple[int, int] = (640, 480),
    spacing_m: float = 2.0,
    lateral_offset_m: float = 1.0,
    heading_offset_deg: float = 4.0,
    along_offset_m: float = 1.0,
) -> Route:
    """The scene and both drives ``generate_sample`` renders (same parameters, same result)."""
    scene = street.build_scene((n_frames - 1) * spacing_m + along_offset_m, seed)
    reference = camera_paths.make_traversal(n_frames, spacing_m, seed=seed, traversal_index=0)
    query = camera_paths.make_traversal(
        n_frames, spacing_m, lateral_offset_m, heading_offset_deg, along_offset_m, seed=seed, traversal_index=1
    )
    return Route(
        scene,
        reference,
        query,
        camera_paths.default_intrinsics(image_size),
        (int(image_size[0]), int(image_size[1])),
        int(seed),
    )


def generate_sample(
    out_dir: str | Path,
    seed: int = 0,
    n_frames: int = 30,
    conditions: Mapping[str, float] | None = None,
    image_size: tuple[int, int] = (640, 480),
    spacing_m: float = 2.0,
    lateral_offset_m: float = 1.0,
    heading_offset_deg: float = 4.0,
    along_offset_m: float = 1.0,
    max_distance_m: float = street.DEFAULT_MAX_DISTANCE_M,
    max_heading_deg: float = street.DEFAULT_MAX_HEADING_DEG,
    force: bool = False,
) -> dict:
    """Write a two-traversal sample: ``day/`` (reference, clear) and ``night/``
    (query, offset viewpoint, ``conditions`` - default a night change), plus
    ``poses.csv``, ``pairs.txt`` and ``generator.json``.

    Skips the work when ``generator.json`` records the same parameters and all
    outputs exist (unless ``force``).  Returns a summary dict.
    """
    out_dir = Path(out_dir)
    conditions = dict(photometry.DEFAULT_NIGHT_CONDITIONS if conditions is None else conditions)
    photometry.validate_conditions(conditions)
    params = {
        "version": GENERATOR_VERSION,
        "seed": int(seed),
        "n_frames": int(n_frames),
        "conditions": {k: float(v) for k, v in sorted(conditions.items())},
        "image_size": [int(image_size[0]), int(image_size[1])],
        "spacing_m": float(spacing_m),
        "lateral_offset_m": float(lateral_offset_m),
        "heading_offset_deg": float(heading_offset_deg),
        "along_offset_m": float(along_offset_m),
        "max_distance_m": float(max_distance_m),
        "max_heading_deg": float(max_heading_deg),
    }
    params_path = out_dir / "generator.json"
    if not force and params_path.exists():
        recorded = json.loads(params_path.read_text())
        if recorded.get("params") == params and _outputs_exist(out_dir, n_frames):
            return recorded["summary"]

    # Invalidate first: an interrupted run must not look complete next time.
    params_path.unlink(missing_ok=True)
    for folder in ("day", "night"):
        for stale in (out_dir / folder).glob("*.png"):
            if stale.stem.isdigit():  # only this generator's frame files
                stale.unlink()
    route = make_route(seed, n_frames, image_size, spacing_m, lateral_offset_m, heading_offset_deg, along_offset_m)
    K, scene, day, night = route.K, route.scene, route.reference, route.query
    day_names = write_traversal_images(out_dir / "day", route.render_reference(), route.name_width)
    night_names = write_traversal_images(out_dir / "night", route.render_query(conditions), route.name_width)

    with open(out_dir / "poses.csv", "w", newline="", encoding="utf-8") as handle:
        writer = csv.DictWriter(handle, fieldnames=POSE_COLUMNS)
        writer.writeheader()
        writer.writerows(_pose_rows("day", day, K, day_names))
        writer.writerows(_pose_rows("night", night, K, night_names))

    pairs = pose_labels.select_pairs(scene, night, day, seed, max_distance_m, max_heading_deg)
    write_pairs(out_dir / "pairs.txt", [(night_names[q], day_names[r], label) for q, r, label in pairs])
    summary = {
        "n_images": 2 * n_frames,
        "n_pairs": len(pairs),
        "n_positives": int(sum(label for _, _, label in pairs)),
        "max_distance_m": float(max_distance_m),
        "max_heading_deg": float(max_heading_deg),
    }
    params_path.write_text(json.dumps({"params": params, "summary": summary}, indent=2))
    return summary


def _outputs_exist(out_dir: Path, n_frames: int) -> bool:
    width = max(3, len(str(n_frames - 1)))
    needed = [out_dir / "poses.csv", out_dir / "pairs.txt"]
    needed += [out_dir / t / f"{i:0{width}d}.png" for t in ("day", "night") for i in range(n_frames)]
    return all(p.exists() for p in needed)
