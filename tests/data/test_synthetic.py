"""Tests for the synthetic street-route generator (gvbench_nb.data.synthetic)."""

from __future__ import annotations

import csv
import hashlib
import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from gvbench_nb.data import synthetic as syn
from gvbench_nb.data.synthetic import poses, render, street

SMALL_SIZE = (320, 240)  # small renders keep the suite fast


@pytest.fixture(scope="module")
def scene() -> street.Scene:
    return street.build_scene(route_length_m=40.0, seed=0)


@pytest.fixture(scope="module")
def small_frame(scene: street.Scene) -> render.RenderedFrame:
    traversal = poses.make_traversal(4, seed=0)
    K = poses.default_intrinsics(SMALL_SIZE)
    return render.render_frame(scene, traversal.rotations[2], traversal.positions[2], K, SMALL_SIZE)


@pytest.fixture(scope="module")
def sample_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("sample")
    syn.generate_sample(out, seed=0, n_frames=16, image_size=SMALL_SIZE)
    return out


def _read_poses(folder: Path) -> dict[str, dict[str, str]]:
    with open(folder / "poses.csv", newline="", encoding="utf-8") as handle:
        return {row["image"]: row for row in csv.DictReader(handle)}


def _sift_matches(image_0: np.ndarray, image_1: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Mutual nearest RootSIFT matches passing the 0.8 ratio test, as two point arrays."""
    points, descriptors = [], []
    for image in (image_0, image_1):
        keypoints, desc = cv2.SIFT_create(nfeatures=8192).detectAndCompute(
            cv2.cvtColor(image, cv2.COLOR_RGB2GRAY), None
        )
        points.append(np.array([k.pt for k in keypoints], dtype=np.float32))
        descriptors.append(np.sqrt(desc / (desc.sum(axis=1, keepdims=True) + 1e-7)).astype(np.float32))
    dist = np.sqrt(np.maximum(2.0 - 2.0 * descriptors[0] @ descriptors[1].T, 0.0))
    nearest = np.argsort(dist, axis=1)[:, :2]
    rows = np.arange(len(dist))
    keep = np.argmin(dist, axis=0)[nearest[:, 0]] == rows
    keep &= dist[rows, nearest[:, 0]] < 0.8 * dist[rows, nearest[:, 1]]
    return points[0][rows[keep]], points[1][nearest[keep, 0]]


def fundamental_from_poses(
    K0: np.ndarray, R0: np.ndarray, t0: np.ndarray, K1: np.ndarray, R1: np.ndarray, t1: np.ndarray
) -> np.ndarray:
    """Ground-truth F of two rendered views (camera-to-world poses): ``x1^T F x0 = 0``, as findFundamentalMat."""
    R0, R1 = np.asarray(R0, dtype=np.float64), np.asarray(R1, dtype=np.float64)
    t0, t1 = np.asarray(t0, dtype=np.float64).ravel(), np.asarray(t1, dtype=np.float64).ravel()
    x, y, z = R1.T @ (t0 - t1)  # camera 0's centre in camera 1
    essential = np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]]) @ (R1.T @ R0)
    F = np.linalg.inv(K1).T @ essential @ np.linalg.inv(K0)
    return F / np.linalg.norm(F)


def _symmetric_epipolar_distance(F: np.ndarray, x0: np.ndarray, x1: np.ndarray) -> np.ndarray:
    h0, h1 = np.column_stack([x0, np.ones(len(x0))]), np.column_stack([x1, np.ones(len(x1))])
    line_in_1, line_in_0 = h0 @ F.T, h1 @ F
    residual = np.abs(np.sum(h1 * line_in_1, axis=1))
    return 0.5 * residual * (1 / np.hypot(*line_in_1[:, :2].T) + 1 / np.hypot(*line_in_0[:, :2].T))


# ------------------------------------------------------------------ pose rule --
def test_pose_rule_labels_on_hand_made_poses_and_thresholds() -> None:
    reference_positions = [
        [3.0, 0.0, 1.7],  # close, heading 1 deg: 2 deg apart across the wrap -> true
        [0.0, 7.9, 1.7],  # just inside 8 m -> true
        [8.1, 0.0, 1.7],  # just outside 8 m -> false
        [1.0, 0.0, 1.7],  # close but heading 45 deg away -> false
        [1.0, 0.0, 1.7],  # close, heading 39 deg away (across the wrap) -> true
        [1.0, 0.0, 1.7],  # close, opposite heading -> false
    ]
    headings = [1.0, 0.0, 0.0, 44.0, 38.0, 179.0]
    labels = poses.pose_rule_labels([[0.0, 0.0, 1.7]], [359.0], reference_positions, headings, 8.0, 40.0)
    assert labels.shape == (1, 6)
    assert labels[0].tolist() == [True, True, False, False, True, False]
    # The thresholds are parameters.
    assert poses.pose_rule_labels([[0, 0, 0]], [0.0], [[20, 0, 0]], [30.0], max_distance_m=25.0, max_heading_deg=40.0)
    assert not poses.pose_rule_labels([[0, 0, 0]], [0.0], [[20, 0, 0]], [30.0], 25.0, max_heading_deg=20.0)


# ------------------------------------------------------------- sample on disk --
def test_sample_layout_and_pair_counts(sample_dir: Path) -> None:
    for traversal in ("day", "night"):
        assert sorted(p.name for p in (sample_dir / traversal).glob("*.png")) == [f"{i:03d}.png" for i in range(16)]
    assert cv2.imread(str(sample_dir / "night" / "007.png")).shape == (SMALL_SIZE[1], SMALL_SIZE[0], 3)
    pairs = [line.split() for line in (sample_dir / "pairs.txt").read_text().splitlines()]
    assert all(
        len(p) == 3 and p[0].startswith("night/") and p[1].startswith("day/") and p[2] in {"0", "1"} for p in pairs
    )
    assert all((sample_dir / p[0]).exists() and (sample_dir / p[1]).exists() for p in pairs)
    per_query: dict[str, list[int]] = {}
    for query, _, label in pairs:
        per_query.setdefault(query, []).append(int(label))
    assert len(per_query) == 16
    for labels in per_query.values():
        assert 6 <= len(labels) <= 10
        assert 1 <= sum(labels) < len(labels)  # every query has positives and negatives


def test_pair_labels_and_rotations_agree_with_poses_csv(sample_dir: Path) -> None:
    rows = _read_poses(sample_dir)
    params = json.loads((sample_dir / "generator.json").read_text())["params"]
    for line in (sample_dir / "pairs.txt").read_text().splitlines():
        query, reference, label = line.split()
        q, r = rows[query], rows[reference]
        position = lambda row: [float(row[c]) for c in "xyz"]
        expected = poses.pose_rule_labels(
            position(q),
            [float(q["yaw_deg"])],
            position(r),
            [float(r["yaw_deg"])],
            params["max_distance_m"],
            params["max_heading_deg"],
        )
        assert bool(expected[0, 0]) == (label == "1"), line
    assert len(rows) == 32
    for row in list(rows.values())[::5]:
        R = np.array([[float(row[f"r{i}{j}"]) for j in range(3)] for i in range(3)])
        expected = poses.camera_rotation(float(row["yaw_deg"]), float(row["pitch_deg"]), float(row["roll_deg"]))
        np.testing.assert_allclose(R, expected, atol=1e-8)
        np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-8)


def test_make_route_is_what_generate_sample_renders(sample_dir: Path) -> None:
    route = syn.make_route(seed=0, n_frames=16, image_size=SMALL_SIZE)
    on_disk = cv2.cvtColor(cv2.imread(str(sample_dir / "night" / "007.png")), cv2.COLOR_BGR2RGB)
    assert np.array_equal(on_disk, route.render_query(render.DEFAULT_NIGHT_CONDITIONS)[7])
    position = [float(_read_poses(sample_dir)["day/003.png"][c]) for c in "xyz"]
    np.testing.assert_allclose(position, route.reference.positions[3], atol=1e-5)


def test_look_alike_pairs_are_false_and_see_the_repeated_block() -> None:
    route = syn.make_route(seed=0, n_frames=30, image_size=SMALL_SIZE)
    look_alike = syn.look_alike_labels(route.scene, route.query, route.reference)
    headings = [poses.heading_from_rotation(t.rotations) for t in (route.query, route.reference)]
    true_pairs = poses.pose_rule_labels(route.query.positions, headings[0], route.reference.positions, headings[1])
    assert look_alike.sum() > 20
    assert not (look_alike & true_pairs).any()
    ((source_x, copy_x, length),) = route.scene.alias_blocks
    for q, r in zip(*np.nonzero(look_alike)):
        query_x, reference_x = route.query.positions[q, 0], route.reference.positions[r, 0]
        # The reference stands within the pose threshold of the query's look-alike position ...
        assert abs(abs(reference_x - query_x) - (copy_x - source_x)) <= syn.DEFAULT_MAX_DISTANCE_M
        # ... and the query is before or beside the block it looks at, not past it.
        seen_from = source_x if reference_x > query_x else copy_x
        assert seen_from - syn.LOOK_ALIKE_LOOK_AHEAD_M <= query_x <= seen_from + 0.5 * length
    # A wider look-ahead only adds look-alikes.
    wider = syn.look_alike_labels(route.scene, route.query, route.reference, look_ahead_m=40.0)
    assert (wider | ~look_alike).all()


def test_generate_sample_skips_when_parameters_match(sample_dir: Path) -> None:
    before = {p: p.stat().st_mtime_ns for p in sample_dir.rglob("*.png")}
    summary = syn.generate_sample(sample_dir, seed=0, n_frames=16, image_size=SMALL_SIZE)
    assert {p: p.stat().st_mtime_ns for p in sample_dir.rglob("*.png")} == before
    assert summary["n_images"] == 32
    assert 0 < summary["n_positives"] < summary["n_pairs"]


def test_same_seed_same_bytes_other_seed_differs(tmp_path: Path) -> None:
    for name, seed in (("a", 3), ("b", 3), ("c", 4)):
        syn.generate_sample(tmp_path / name, seed=seed, n_frames=5, image_size=(160, 120))
    digest_a, digest_b, digest_c = (
        {
            str(p.relative_to(tmp_path / n)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in (tmp_path / n).rglob("*.*")
        }
        for n in "abc"
    )
    assert digest_a == digest_b and {"poses.csv", "pairs.txt", "night/002.png"} <= set(digest_a)
    assert digest_a["night/002.png"] != digest_c["night/002.png"]
    assert digest_a["day/002.png"] != digest_c["day/002.png"]


def test_changed_parameters_regenerate(tmp_path: Path) -> None:
    syn.generate_sample(tmp_path, seed=0, n_frames=4, image_size=(160, 120))
    night_clear = (tmp_path / "night" / "001.png").read_bytes()
    syn.generate_sample(tmp_path, seed=0, n_frames=4, image_size=(160, 120), conditions={"illumination": 0.0})
    assert (tmp_path / "night" / "001.png").read_bytes() != night_clear


def test_render_does_not_depend_on_worker_count(scene: street.Scene) -> None:
    traversal = poses.make_traversal(3, seed=0)
    K = poses.default_intrinsics((160, 120))
    conditions = {"illumination": 0.5, "weather": 0.3}
    serial = syn.render_traversal(scene, traversal, K, (160, 120), conditions, seed=1, workers=1)
    threaded = syn.render_traversal(scene, traversal, K, (160, 120), conditions, seed=1, workers=2)
    assert all(np.array_equal(a, b) for a, b in zip(serial, threaded))


# ----------------------------------------------------------------- conditions --
def _apply(frame: render.RenderedFrame, conditions: dict[str, float], seed: int = 0) -> np.ndarray:
    return render.apply_conditions(frame, conditions, np.random.default_rng(seed))


def test_zero_strength_leaves_image_byte_identical(small_frame: render.RenderedFrame) -> None:
    for conditions in [{}, dict.fromkeys(syn.CONDITIONS, 0.0)] + [{name: 0.0} for name in syn.CONDITIONS]:
        out = _apply(small_frame, conditions)
        assert out.dtype == np.uint8 and out.tobytes() == small_frame.image.tobytes()


@pytest.mark.parametrize("name", syn.CONDITIONS)
def test_positive_strength_changes_image(small_frame: render.RenderedFrame, name: str) -> None:
    clear = small_frame.image.astype(np.int16)
    change_weak, change_strong = (
        np.abs(_apply(small_frame, {name: s}).astype(np.int16) - clear).mean() for s in (0.2, 0.9)
    )
    assert change_weak > 0.5
    assert change_strong > change_weak  # strength is monotone in effect size


def test_conditions_are_seeded(small_frame: render.RenderedFrame) -> None:
    conditions = {"illumination": 0.7, "weather": 0.5}
    assert np.array_equal(_apply(small_frame, conditions, seed=5), _apply(small_frame, conditions, seed=5))
    assert not np.array_equal(_apply(small_frame, conditions, seed=5), _apply(small_frame, conditions, seed=6))


def test_conditions_compose(small_frame: render.RenderedFrame) -> None:
    singles = {name: _apply(small_frame, {name: 0.6}) for name in syn.CONDITIONS}
    combos = [("illumination", "season"), ("illumination", "weather"), ("season", "weather"), syn.CONDITIONS]
    for combo in combos:
        out = _apply(small_frame, dict.fromkeys(combo, 0.6))
        assert out.shape == small_frame.image.shape and out.dtype == np.uint8
        for name in combo:  # the combination is not just one of its parts
            assert np.abs(out.astype(np.int16) - singles[name].astype(np.int16)).mean() > 0.5


def test_season_whitens_upward_surfaces_only(small_frame: render.RenderedFrame) -> None:
    change = (_apply(small_frame, {"season": 1.0}).astype(np.float32) - small_frame.image).mean(axis=2)
    ground = small_frame.normals[..., 2] > 0.9
    facade = (np.abs(small_frame.normals[..., 2]) < 0.1) & np.isfinite(small_frame.depth)
    assert change[ground].mean() > 40.0
    assert abs(change[facade].mean()) < 20.0


def test_fog_grows_with_depth(small_frame: render.RenderedFrame) -> None:
    foggy = _apply(small_frame, {"weather": 1.0}).astype(np.float32)
    depth = small_frame.depth
    near, far = depth < 8.0, np.isfinite(depth) & (depth > 30.0)
    assert near.any() and far.any()
    # Fog pulls far surfaces towards the airlight more than near ones.
    airlight_distance = np.abs(foggy - foggy[np.isinf(depth)].mean(axis=0)).mean(axis=2)
    assert airlight_distance[far].mean() < airlight_distance[near].mean()
    assert np.abs(foggy - small_frame.image).mean(axis=2)[far].mean() > 0


@pytest.mark.parametrize("conditions", [{"sandstorm": 0.5}, {"weather": 1.5}])
def test_unknown_condition_or_bad_strength_rejected(small_frame: render.RenderedFrame, conditions) -> None:
    with pytest.raises(ValueError):
        _apply(small_frame, conditions)


# ------------------------------------------------------------------- geometry --
def test_fundamental_from_poses_on_projected_points() -> None:
    rng = np.random.default_rng(0)
    K = poses.default_intrinsics()
    R0, t0 = poses.camera_rotation(3.0, 1.0, -0.5), np.array([0.0, 0.2, 1.7])
    R1, t1 = poses.camera_rotation(-5.0, 0.0, 0.8), np.array([4.0, -0.8, 1.6])
    points = np.column_stack([rng.uniform(10, 40, 50), rng.uniform(-10, 10, 50), rng.uniform(0, 8, 50)])

    def project(R: np.ndarray, t: np.ndarray) -> np.ndarray:
        uv = (points - t) @ R @ K.T  # world -> camera: R^T (X - t)
        return uv[:, :2] / uv[:, 2:3]

    F = fundamental_from_poses(K, R0, t0, K, R1, t1)
    assert _symmetric_epipolar_distance(F, project(R0, t0), project(R1, t1)).max() < 1e-6


def test_ground_truth_F_agrees_with_sift_on_true_pair(scene: street.Scene) -> None:
    size = (640, 480)
    K = poses.default_intrinsics(size)
    reference = poses.make_traversal(12, seed=0, traversal_index=0)
    query = poses.make_traversal(
        12, lateral_offset_m=1.0, heading_offset_deg=4.0, along_offset_m=1.0, seed=0, traversal_index=1
    )
    q, r = 8, 9  # 1 m apart along the street, 1 m laterally, ~4 deg in heading
    assert poses.pose_rule_labels(
        query.positions[q], [query.yaw_deg[q]], reference.positions[r], [reference.yaw_deg[r]]
    )
    image_r = render.render_frame(scene, reference.rotations[r], reference.positions[r], K, size).image
    image_q = render.render_frame(scene, query.rotations[q], query.positions[q], K, size).image
    x_r, x_q = _sift_matches(image_r, image_q)
    cv2.setRNGSeed(0)
    _, mask = cv2.findFundamentalMat(x_r, x_q, cv2.FM_RANSAC, 3.0, 0.99, 1000)
    inliers = mask.ravel().astype(bool)
    assert inliers.sum() >= 50
    F = fundamental_from_poses(
        K, reference.rotations[r], reference.positions[r], K, query.rotations[q], query.positions[q]
    )
    assert np.median(_symmetric_epipolar_distance(F, x_r[inliers], x_q[inliers])) < 2.0
