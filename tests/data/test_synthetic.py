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

SMALL_SIZE = (320, 240)  # small renders keep the suite fast


# ----------------------------------------------------------------------------
# Fixtures
# ----------------------------------------------------------------------------


@pytest.fixture(scope="module")
def scene() -> syn.Scene:
    return syn.build_scene(route_length_m=40.0, seed=0)


@pytest.fixture(scope="module")
def small_frame(scene: syn.Scene) -> syn.RenderedFrame:
    traversal = syn.make_traversal(4, seed=0)
    K = syn.default_intrinsics(SMALL_SIZE)
    return syn.render_frame(scene, traversal.rotations[2], traversal.positions[2], K, SMALL_SIZE)


@pytest.fixture(scope="module")
def sample_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("sample")
    syn.generate_sample(out, seed=0, n_frames=16, image_size=SMALL_SIZE)
    return out


def _digest_tree(folder: Path) -> dict[str, str]:
    """sha256 of every image, pose and pair file under ``folder``."""
    files = sorted(folder.rglob("*.png")) + [folder / "poses.csv", folder / "pairs.txt"]
    return {str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest() for p in files}


def _read_poses(folder: Path) -> dict[str, tuple[np.ndarray, float]]:
    with open(folder / "poses.csv", newline="", encoding="utf-8") as handle:
        return {
            row["image"]: (np.array([float(row[c]) for c in "xyz"]), float(row["yaw_deg"]))
            for row in csv.DictReader(handle)
        }


def _sift_rootsift(image: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    sift = cv2.SIFT_create(nfeatures=8192)
    keypoints, desc = sift.detectAndCompute(cv2.cvtColor(image, cv2.COLOR_RGB2GRAY), None)
    desc = np.sqrt(desc / (desc.sum(axis=1, keepdims=True) + 1e-7)).astype(np.float32)
    return np.array([k.pt for k in keypoints], dtype=np.float32), desc


def _mutual_ratio_matches(d0: np.ndarray, d1: np.ndarray, ratio: float = 0.8) -> np.ndarray:
    dist = np.sqrt(np.maximum(2.0 - 2.0 * d0 @ d1.T, 0.0))
    nearest = np.argsort(dist, axis=1)[:, :2]
    rows = np.arange(len(d0))
    mutual = np.argmin(dist, axis=0)[nearest[:, 0]] == rows
    distinct = dist[rows, nearest[:, 0]] < ratio * dist[rows, nearest[:, 1]]
    keep = mutual & distinct
    return np.stack([rows[keep], nearest[keep, 0]], axis=1)


def _symmetric_epipolar_distance(F: np.ndarray, x0: np.ndarray, x1: np.ndarray) -> np.ndarray:
    h0 = np.column_stack([x0, np.ones(len(x0))])
    h1 = np.column_stack([x1, np.ones(len(x1))])
    line_in_1, line_in_0 = h0 @ F.T, h1 @ F
    residual = np.abs(np.sum(h1 * line_in_1, axis=1))
    return 0.5 * (
        residual / np.hypot(line_in_1[:, 0], line_in_1[:, 1]) + residual / np.hypot(line_in_0[:, 0], line_in_0[:, 1])
    )


# ----------------------------------------------------------------------------
# Pose rule
# ----------------------------------------------------------------------------


def test_heading_difference_wraps_around() -> None:
    assert syn.heading_difference_deg(359.0, 1.0) == pytest.approx(2.0)
    assert syn.heading_difference_deg(-170.0, 170.0) == pytest.approx(20.0)
    assert syn.heading_difference_deg(0.0, 180.0) == pytest.approx(180.0)
    assert syn.heading_difference_deg(10.0, 370.0) == pytest.approx(0.0)


def test_pose_rule_labels_on_hand_made_poses() -> None:
    query_positions = np.array([[0.0, 0.0, 1.7]])
    query_headings = np.array([359.0])
    reference_positions = np.array(
        [
            [3.0, 0.0, 1.7],  # close, heading 1 deg: 2 deg apart across the wrap -> true
            [0.0, 7.9, 1.7],  # just inside 8 m -> true
            [8.1, 0.0, 1.7],  # just outside 8 m -> false
            [1.0, 0.0, 1.7],  # close but heading 45 deg away -> false
            [1.0, 0.0, 1.7],  # close, heading 39 deg away (across the wrap) -> true
            [1.0, 0.0, 1.7],  # close, opposite heading -> false
        ]
    )
    reference_headings = np.array([1.0, 0.0, 0.0, 44.0, 38.0, 179.0])
    labels = syn.pose_rule_labels(
        query_positions,
        query_headings,
        reference_positions,
        reference_headings,
        max_distance_m=8.0,
        max_heading_deg=40.0,
    )
    assert labels.shape == (1, 6)
    assert labels[0].tolist() == [True, True, False, False, True, False]


def test_pose_rule_thresholds_are_parameters() -> None:
    labels = syn.pose_rule_labels([[0, 0, 0]], [0.0], [[20, 0, 0]], [30.0], max_distance_m=25.0, max_heading_deg=40.0)
    assert labels[0, 0]
    labels = syn.pose_rule_labels([[0, 0, 0]], [0.0], [[20, 0, 0]], [30.0], max_distance_m=25.0, max_heading_deg=20.0)
    assert not labels[0, 0]


# ----------------------------------------------------------------------------
# Sample on disk
# ----------------------------------------------------------------------------


def test_sample_layout_and_pair_counts(sample_dir: Path) -> None:
    assert len(list((sample_dir / "day").glob("*.png"))) == 16
    assert len(list((sample_dir / "night").glob("*.png"))) == 16
    assert (sample_dir / "day" / "000.png").exists()
    image = cv2.imread(str(sample_dir / "night" / "007.png"))
    assert image.shape == (SMALL_SIZE[1], SMALL_SIZE[0], 3)

    lines = (sample_dir / "pairs.txt").read_text().splitlines()
    pairs = [line.split() for line in lines]
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


def test_pair_labels_agree_with_poses(sample_dir: Path) -> None:
    poses = _read_poses(sample_dir)
    params = json.loads((sample_dir / "generator.json").read_text())["params"]
    for line in (sample_dir / "pairs.txt").read_text().splitlines():
        query, reference, label = line.split()
        (q_pos, q_yaw), (r_pos, r_yaw) = poses[query], poses[reference]
        expected = syn.pose_rule_labels(
            q_pos, [q_yaw], r_pos, [r_yaw], params["max_distance_m"], params["max_heading_deg"]
        )
        assert bool(expected[0, 0]) == (label == "1"), line


def test_poses_csv_rotation_matches_angles(sample_dir: Path) -> None:
    with open(sample_dir / "poses.csv", newline="", encoding="utf-8") as handle:
        rows = list(csv.DictReader(handle))
    assert len(rows) == 32
    for row in rows[::5]:
        R = np.array([[float(row[f"r{i}{j}"]) for j in range(3)] for i in range(3)])
        expected = syn.camera_rotation(float(row["yaw_deg"]), float(row["pitch_deg"]), float(row["roll_deg"]))
        np.testing.assert_allclose(R, expected, atol=1e-8)
        np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-8)


def test_make_route_is_what_generate_sample_renders(sample_dir: Path) -> None:
    route = syn.make_route(seed=0, n_frames=16, image_size=SMALL_SIZE)
    frame = 7
    on_disk = cv2.cvtColor(cv2.imread(str(sample_dir / "night" / f"{frame:03d}.png")), cv2.COLOR_BGR2RGB)
    night = syn.render_frame(
        route.scene, route.query.rotations[frame], route.query.positions[frame], route.K, SMALL_SIZE
    )
    expected = syn.apply_conditions(
        night.image,
        night.depth,
        night.normals,
        syn.DEFAULT_NIGHT_CONDITIONS,
        syn.frame_rng(0, 1, frame),
        light_points=night.light_points,
    )
    assert np.array_equal(on_disk, expected)
    poses = _read_poses(sample_dir)
    np.testing.assert_allclose(poses["day/003.png"][0], route.reference.positions[3], atol=1e-5)


def test_look_alike_pairs_are_false_and_see_the_repeated_block() -> None:
    route = syn.make_route(seed=0, n_frames=30, image_size=SMALL_SIZE)
    look_alike = syn.look_alike_labels(route.scene, route.query, route.reference)
    true_pairs = syn.pose_rule_labels(
        route.query.positions,
        syn.heading_from_rotation(route.query.rotations),
        route.reference.positions,
        syn.heading_from_rotation(route.reference.rotations),
    )
    assert look_alike.sum() > 20
    assert not (look_alike & true_pairs).any()
    ((source_x, copy_x, length),) = route.scene.alias_blocks
    shift = copy_x - source_x
    for q, r in zip(*np.nonzero(look_alike)):
        query_x, reference_x = route.query.positions[q, 0], route.reference.positions[r, 0]
        # The reference stands within the pose threshold of the query's look-alike position.
        assert abs(abs(reference_x - query_x) - shift) <= syn.DEFAULT_MAX_DISTANCE_M
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
    kwargs: dict = {"n_frames": 5, "image_size": (160, 120)}
    syn.generate_sample(tmp_path / "a", seed=3, **kwargs)
    syn.generate_sample(tmp_path / "b", seed=3, **kwargs)
    syn.generate_sample(tmp_path / "c", seed=4, **kwargs)
    digest_a, digest_b, digest_c = (_digest_tree(tmp_path / n) for n in "abc")
    assert digest_a == digest_b
    assert digest_a["night/002.png"] != digest_c["night/002.png"]
    assert digest_a["day/002.png"] != digest_c["day/002.png"]


def test_changed_parameters_regenerate(tmp_path: Path) -> None:
    syn.generate_sample(tmp_path, seed=0, n_frames=4, image_size=(160, 120))
    night_clear = (tmp_path / "night" / "001.png").read_bytes()
    syn.generate_sample(tmp_path, seed=0, n_frames=4, image_size=(160, 120), conditions={"illumination": 0.0})
    assert (tmp_path / "night" / "001.png").read_bytes() != night_clear


def test_render_does_not_depend_on_worker_count(scene: syn.Scene) -> None:
    traversal = syn.make_traversal(3, seed=0)
    K = syn.default_intrinsics((160, 120))
    conditions = {"illumination": 0.5, "weather": 0.3}
    serial = syn.render_traversal(scene, traversal, K, (160, 120), conditions, seed=1, workers=1)
    threaded = syn.render_traversal(scene, traversal, K, (160, 120), conditions, seed=1, workers=2)
    assert all(np.array_equal(a, b) for a, b in zip(serial, threaded))


# ----------------------------------------------------------------------------
# Conditions
# ----------------------------------------------------------------------------


def _apply(frame: syn.RenderedFrame, conditions: dict[str, float], seed: int = 0) -> np.ndarray:
    return syn.apply_conditions(
        frame.image,
        frame.depth,
        frame.normals,
        conditions,
        np.random.default_rng(seed),
        light_points=frame.light_points,
    )


def test_zero_strength_leaves_image_byte_identical(small_frame: syn.RenderedFrame) -> None:
    assert np.array_equal(_apply(small_frame, {}), small_frame.image)
    assert np.array_equal(_apply(small_frame, dict.fromkeys(syn.CONDITIONS, 0.0)), small_frame.image)
    for name in syn.CONDITIONS:
        out = _apply(small_frame, {name: 0.0})
        assert out.dtype == np.uint8 and out.tobytes() == small_frame.image.tobytes()


@pytest.mark.parametrize("name", syn.CONDITIONS)
def test_positive_strength_changes_image(small_frame: syn.RenderedFrame, name: str) -> None:
    weak, strong = _apply(small_frame, {name: 0.2}), _apply(small_frame, {name: 0.9})
    clear = small_frame.image.astype(np.int16)
    change_weak = np.abs(weak.astype(np.int16) - clear).mean()
    change_strong = np.abs(strong.astype(np.int16) - clear).mean()
    assert change_weak > 0.5
    assert change_strong > change_weak  # strength is monotone in effect size


def test_conditions_are_seeded(small_frame: syn.RenderedFrame) -> None:
    conditions = {"illumination": 0.7, "weather": 0.5}
    assert np.array_equal(_apply(small_frame, conditions, seed=5), _apply(small_frame, conditions, seed=5))
    assert not np.array_equal(_apply(small_frame, conditions, seed=5), _apply(small_frame, conditions, seed=6))


def test_conditions_compose(small_frame: syn.RenderedFrame) -> None:
    singles = {name: _apply(small_frame, {name: 0.6}) for name in syn.CONDITIONS}
    combos = [("illumination", "season"), ("illumination", "weather"), ("season", "weather"), syn.CONDITIONS]
    for combo in combos:
        out = _apply(small_frame, dict.fromkeys(combo, 0.6))
        assert out.shape == small_frame.image.shape and out.dtype == np.uint8
        for name in combo:  # the combination is not just one of its parts
            assert np.abs(out.astype(np.int16) - singles[name].astype(np.int16)).mean() > 0.5


def test_season_whitens_upward_surfaces_only(small_frame: syn.RenderedFrame) -> None:
    snowy = _apply(small_frame, {"season": 1.0}).astype(np.float32).mean(axis=2)
    clear = small_frame.image.astype(np.float32).mean(axis=2)
    ground = small_frame.normals[..., 2] > 0.9
    facade = np.abs(small_frame.normals[..., 2]) < 0.1
    facade &= np.isfinite(small_frame.depth)
    assert (snowy - clear)[ground].mean() > 40.0
    assert abs((snowy - clear)[facade].mean()) < 20.0


def test_fog_grows_with_depth(small_frame: syn.RenderedFrame) -> None:
    foggy = _apply(small_frame, {"weather": 1.0}).astype(np.float32)
    clear = small_frame.image.astype(np.float32)
    change = np.abs(foggy - clear).mean(axis=2)
    depth = small_frame.depth
    near, far = depth < 8.0, np.isfinite(depth) & (depth > 30.0)
    assert near.any() and far.any()
    # Fog pulls far surfaces towards the airlight more than near ones.
    airlight_distance = np.abs(foggy - foggy[np.isinf(depth)].mean(axis=0)).mean(axis=2)
    assert airlight_distance[far].mean() < airlight_distance[near].mean()
    assert change[far].mean() > 0


def test_unknown_condition_or_bad_strength_rejected(small_frame: syn.RenderedFrame) -> None:
    with pytest.raises(ValueError):
        _apply(small_frame, {"sandstorm": 0.5})
    with pytest.raises(ValueError):
        _apply(small_frame, {"weather": 1.5})


# ----------------------------------------------------------------------------
# Geometry
# ----------------------------------------------------------------------------


def test_fundamental_from_poses_on_projected_points() -> None:
    rng = np.random.default_rng(0)
    K = syn.default_intrinsics()
    R0, t0 = syn.camera_rotation(3.0, 1.0, -0.5), np.array([0.0, 0.2, 1.7])
    R1, t1 = syn.camera_rotation(-5.0, 0.0, 0.8), np.array([4.0, -0.8, 1.6])
    points = np.column_stack([rng.uniform(10, 40, 50), rng.uniform(-10, 10, 50), rng.uniform(0, 8, 50)])

    def project(R: np.ndarray, t: np.ndarray) -> np.ndarray:
        cam = (points - t) @ R  # world -> camera: R^T (X - t)
        uv = cam @ K.T
        return uv[:, :2] / uv[:, 2:3]

    F = syn.fundamental_from_poses(K, R0, t0, K, R1, t1)
    distance = _symmetric_epipolar_distance(F, project(R0, t0), project(R1, t1))
    assert distance.max() < 1e-6


def test_ground_truth_F_agrees_with_sift_on_true_pair(scene: syn.Scene) -> None:
    size = (640, 480)
    K = syn.default_intrinsics(size)
    reference = syn.make_traversal(12, seed=0, traversal_index=0)
    query = syn.make_traversal(
        12, lateral_offset_m=1.0, heading_offset_deg=4.0, along_offset_m=1.0, seed=0, traversal_index=1
    )
    q, r = 8, 9  # 1 m apart along the street, 1 m laterally, ~4 deg in heading
    labels = syn.pose_rule_labels(
        query.positions[q], [query.yaw_deg[q]], reference.positions[r], [reference.yaw_deg[r]]
    )
    assert labels[0, 0]
    image_r = syn.render_frame(scene, reference.rotations[r], reference.positions[r], K, size).image
    image_q = syn.render_frame(scene, query.rotations[q], query.positions[q], K, size).image
    (p_r, d_r), (p_q, d_q) = _sift_rootsift(image_r), _sift_rootsift(image_q)
    matches = _mutual_ratio_matches(d_r, d_q)
    x_r, x_q = p_r[matches[:, 0]], p_q[matches[:, 1]]
    cv2.setRNGSeed(0)
    _, mask = cv2.findFundamentalMat(x_r, x_q, cv2.FM_RANSAC, 3.0, 0.99, 1000)
    inliers = mask.ravel().astype(bool)
    assert inliers.sum() >= 50
    F = syn.fundamental_from_poses(
        K, reference.rotations[r], reference.positions[r], K, query.rotations[q], query.positions[q]
    )
    distance = _symmetric_epipolar_distance(F, x_r[inliers], x_q[inliers])
    assert np.median(distance) < 2.0
