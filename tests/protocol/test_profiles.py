"""The protocol profiles: the few-matches rule, the repository profile's image chain and
its verification in resized coordinates."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
from PIL import Image

from gvbench_nb import methods
from gvbench_nb.protocol import images, ransac


# ------------------------------------------------------------ few-matches rule --
def five_matches() -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(0)
    points = rng.uniform(0, 500, (5, 2))
    return points, points + 3.0


@pytest.mark.parametrize("rule", ["zero", "all"])
def test_few_matches_rule_applies_below_the_minimum_and_without_a_model(rule):
    counted = rule == "all"
    points0, points1 = five_matches()
    assert ransac.fit_inliers(points0, points1, few_matches=rule).sum() == 5 * counted
    # min_matches above 8 applies the rule to pairs a fit could take.
    points0 = np.random.default_rng(1).uniform(0, 500, (12, 2))
    assert ransac.fit_inliers(points0, points0 + 2, min_matches=20, few_matches=rule).sum() == 12 * counted
    # Ten copies of one point: OpenCV's RANSAC finds no fundamental matrix (F is None).
    points = np.zeros((10, 2))
    assert ransac.fit_inliers(points, points + 1, few_matches=rule).sum() == 10 * counted


def test_unknown_few_matches_rule_is_one_sentence():
    points0, points1 = five_matches()
    with pytest.raises(ValueError, match="unknown few_matches rule 'some'.*Known: zero, all"):
        ransac.fit_inliers(points0, points1, few_matches="some")


def test_verify_matches_without_score_filter_keeps_low_scores():
    points0, points1 = five_matches()
    matches = np.repeat(np.arange(5)[:, None], 2, axis=1)
    conf = {**methods.resolve_method("sift-nn", "repository")["verifier"], "coordinates": "original"}
    result = ransac.verify_matches(points0, points1, matches, np.full(5, 0.1), conf)
    assert (result["num_matches_filtered"], result["num_inliers"]) == (5, 5)
    paper = methods.resolve_method("sift-nn", "paper")["verifier"]
    result = ransac.verify_matches(points0, points1, matches, np.full(5, 0.1), paper)
    assert (result["num_matches_filtered"], result["num_inliers"]) == (0, 0)


# ------------------------------------------------- resized-coordinate verifying --
def two_view_points(n: int = 200, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Exact projections of random 3-D points into two 1280x960 cameras a metre apart."""
    rng = np.random.default_rng(seed)
    world = np.column_stack([rng.uniform(-4, 4, n), rng.uniform(-3, 3, n), rng.uniform(6, 20, n)])
    K = np.array([[800.0, 0, 640], [0, 800, 480], [0, 0, 1]])
    angle = np.deg2rad(5)
    R = np.array([[np.cos(angle), 0, np.sin(angle)], [0, 1, 0], [-np.sin(angle), 0, np.cos(angle)]])
    t = np.array([1.0, 0.0, 0.2])

    def project(points: np.ndarray) -> np.ndarray:
        pixels = points @ K.T
        return pixels[:, :2] / pixels[:, 2:]

    return project(world), project(world @ R.T + t)


def test_to_verifier_frame_maps_pixel_centres():
    conf = {"coordinates": "resize_to", "resize_to": [512, 288]}
    corners = np.array([[-0.5, -0.5], [1279.5, 959.5]])
    mapped = ransac.to_verifier_frame(corners, np.array([1280, 960]), conf)
    np.testing.assert_allclose(mapped, [[-0.5, -0.5], [511.5, 287.5]])
    assert ransac.to_verifier_frame(corners, None, {"coordinates": "original"}) is corners
    with pytest.raises(ValueError, match="no original image size"):  # it says what to do
        ransac.to_verifier_frame(corners, None, conf)


def test_resized_coordinates_change_which_matches_are_inliers():
    """Errors of 5 px along y in a 960-px-high image are 1.5 px at 288 px high: outliers at the
    paper's 3 px threshold in original pixels, inliers in the repository's 512x288 frame."""
    points0, points1 = two_view_points()
    noisy = points1.copy()
    noisy[:40, 1] += np.where(np.arange(40) % 2, 5.0, -5.0)
    matches = np.repeat(np.arange(len(points0))[:, None], 2, axis=1)
    scores = np.ones(len(points0))
    sizes = (np.array([1280, 960]), np.array([1280, 960]))
    base = {
        "type": "fundamental",
        "method": "FM_RANSAC",
        "threshold_px": 3.0,
        "confidence": 0.999,
        "max_iters": 5000,
        "min_matches": 8,
        "few_matches": "zero",
        "min_match_score": None,
    }
    original = ransac.verify_matches(
        points0, noisy, matches, scores, {**base, "coordinates": "original"}, image_sizes=sizes
    )
    resized = ransac.verify_matches(
        points0,
        noisy,
        matches,
        scores,
        {**base, "coordinates": "resize_to", "resize_to": [512, 288]},
        image_sizes=sizes,
    )
    assert original["inlier_mask"][40:].mean() > 0.95 and original["inlier_mask"][:40].mean() < 0.2
    assert resized["inlier_mask"].mean() > 0.95


def test_bilinear_antialias_resize_equals_pil_bilinear():
    """torchvision's antialiased bilinear Resize (the fork's) and PIL's BILINEAR share one
    algorithm; PIL serves as the independent reference, shrinking and enlarging."""
    rng = np.random.default_rng(0)
    image = (rng.random((96, 128)) * 255).astype(np.float32)
    for size in ((52, 29), (256, 192)):
        ours = images.resize_bilinear_antialias(image, size)
        theirs = np.asarray(Image.fromarray(image, mode="F").resize(size, Image.BILINEAR))
        np.testing.assert_allclose(ours, theirs, atol=1e-3)


def test_repository_image_chain_sizes_and_scale(tmp_path):
    rng = np.random.default_rng(0)
    path = tmp_path / "frame.png"
    Image.fromarray((rng.random((960, 1280, 3)) * 255).astype(np.uint8)).save(path)
    sift = methods.resolve_method("sift-nn", "repository")["extractor"]
    image, scale = images.load_for_extraction(path, sift)
    # Made 8-bit once, at the end of the chain, and handed on as float32 like every image.
    assert image.shape == (288, 512) and image.dtype == np.float32 and np.array_equal(image, np.round(image))
    # Min-max stretched, as the fork's OpenCV matchers do; its truncation can take the top to 254.
    assert image.min() == 0 and image.max() >= 254
    np.testing.assert_allclose(scale, [1280 / 512, 960 / 288], rtol=1e-6)
    disk = methods.resolve_method("disk-lg", "repository")["extractor"]
    image, scale = images.load_for_extraction(path, disk)
    assert image.shape == (576, 1024, 3)  # 512x288, then LightGlue's extractor input at 1024 on the long side
    np.testing.assert_allclose(scale, [1280 / 1024, 960 / 576], rtol=1e-6)


def test_repository_opencv_image_is_truncated_as_the_fork_makes_it(tmp_path):
    """The fork's OpenCV matchers take ToTensor's x / 255, grey it with cvtColor, stretch it
    with cv2.normalize(NORM_MINMAX) and make it 8-bit with astype("uint8"): truncation. At
    512x288 no resize runs, so the steps are the published ones, written out here."""
    rng = np.random.default_rng(1)
    rgb = (rng.random((288, 512, 3)) * 255).astype(np.uint8)
    path = tmp_path / "frame.png"
    Image.fromarray(rgb).save(path)
    grey = cv2.cvtColor(rgb.astype(np.float32) / np.float32(255.0), cv2.COLOR_RGB2GRAY)
    theirs = cv2.normalize(grey, None, 0, 255, cv2.NORM_MINMAX).astype("uint8")
    for method in ("orb-nn", "sift-nn"):
        ours, _ = images.load_for_extraction(path, methods.resolve_method(method, "repository")["extractor"])
        np.testing.assert_array_equal(ours, theirs.astype(np.float32))


def test_exif_orientation_is_applied_as_hloc_reads_and_ignored_as_pil_loads(tmp_path):
    """hloc reads with cv2.imread (IMREAD_GRAYSCALE / IMREAD_COLOR), which turns the image by
    its EXIF orientation; the repository's PIL ``Image.open().convert("RGB")`` does not."""
    rgb = np.zeros((40, 80, 3), np.uint8)
    rgb[:, :10] = 255
    picture = Image.fromarray(rgb)
    exif = picture.getexif()
    exif[0x0112] = 6  # rotate 90 degrees clockwise to display
    path = tmp_path / "turned.jpg"
    picture.save(path, "JPEG", exif=exif.tobytes())
    paper = methods.resolve_method("sift-nn", "paper")["extractor"]
    image, _ = images.load_for_extraction(path, paper)
    np.testing.assert_array_equal(image, cv2.imread(str(path), cv2.IMREAD_GRAYSCALE).astype(np.float32))
    assert image.shape == (80, 40)
    repository = methods.resolve_method("orb-nn", "repository")["extractor"]
    _, scale = images.load_for_extraction(path, repository)
    with Image.open(path) as loaded:
        assert loaded.convert("RGB").size == (80, 40)  # PIL: width 80, as stored
    np.testing.assert_allclose(scale, [80 / 512, 40 / 288], rtol=1e-6)


@pytest.mark.parametrize(("width", "height", "shrunk"), [(960, 540, (960, 540)), (1100, 700, (1024, 652))])
def test_paper_loftr_input_floors_to_eight_in_a_second_bilinear_resize(tmp_path, width, height, shrunk):
    """hloc's match_dense: INTER_AREA only when shrinking to 1024, then each side floored to a
    multiple of 8 by torchvision's bilinear resize of the [0, 1] tensor (PIL's BILINEAR is the
    same algorithm, the independent reference here), not one resize to the floored size."""
    rng = np.random.default_rng(4)
    grey = (rng.random((height, width)) * 255).astype(np.uint8)
    path = tmp_path / "frame.png"
    Image.fromarray(grey).save(path)
    conf = methods.resolve_method("loftr", "paper")["matcher"]
    first = grey.astype(np.float32)
    if shrunk != (width, height):
        first = cv2.resize(first, shrunk, interpolation=cv2.INTER_AREA)
    floored = (shrunk[0] // 8 * 8, shrunk[1] // 8 * 8)
    second = Image.fromarray(first / np.float32(255.0), mode="F").resize(floored, Image.BILINEAR)
    ours, scale = images.load_for_extraction(path, conf)
    assert ours.shape == (floored[1], floored[0])
    np.testing.assert_allclose(ours, np.asarray(second) * 255, atol=0.02)  # PIL and torch round apart
    np.testing.assert_allclose(scale, [width / floored[0], height / floored[1]], rtol=1e-6)


def opencv_knn_ratio(descriptors0: np.ndarray, descriptors1: np.ndarray, norm: int) -> list[tuple[int, int]]:
    """The fork's handcrafted matcher rule: BFMatcher(norm).knnMatch(k=2), kept when
    m.distance < 0.75 * n.distance."""
    pairs = cv2.BFMatcher(norm).knnMatch(descriptors0, descriptors1, k=2)
    return [(m.queryIdx, m.trainIdx) for m, n in pairs if m.distance < 0.75 * n.distance]


def repository_matches(method: str, descriptors0: np.ndarray, descriptors1: np.ndarray) -> list[tuple[int, int]]:
    from gvbench_nb.protocol.matching import build_matcher

    matcher = build_matcher(methods.resolve_method(method, "repository")["matcher"], "cpu")
    features = [
        {"keypoints": np.zeros((len(d), 2), np.float32), "descriptors": d} for d in (descriptors0, descriptors1)
    ]
    matches, _ = matcher(*features)
    return [tuple(int(i) for i in row) for row in matches]


def test_repository_orb_ratio_test_is_strict_on_hamming_bits():
    """Integer Hamming distances reach the ratio exactly: 3 bits against 4 is not < 0.75 x 4,
    so the fork drops it (hloc's <= would keep it); 2 against 4 passes."""
    query = np.zeros((2, 32), np.uint8)
    query[1, 31] = 0xFF  # the second query: 8 bits from the first
    train = np.zeros((4, 32), np.uint8)
    train[0, 0] = 0b111  # 3 bits from query 0
    train[1, 0] = 0b1111  # 4 bits from query 0
    train[2, 31], train[2, 0] = 0xFF, 0b11  # 2 bits from query 1
    train[3, 31], train[3, 0] = 0xFF, 0b1111  # 4 bits from query 1
    expected = opencv_knn_ratio(query, train, cv2.NORM_HAMMING)
    assert expected == [(1, 2)]
    assert repository_matches("orb-nn", query, train) == expected
    rng = np.random.default_rng(2)
    random0, random1 = (rng.integers(0, 256, (n, 32), dtype=np.uint8) for n in (300, 280))
    random1[:100] = random0[:100] ^ (rng.random((100, 32)) < 0.05).astype(np.uint8)  # near copies
    assert repository_matches("orb-nn", random0, random1) == opencv_knn_ratio(random0, random1, cv2.NORM_HAMMING)


def test_repository_sift_matches_raw_descriptors_by_opencv_l2():
    """The fork's BFMatcher compares raw SIFT descriptors: the nearest by L2 distance, which
    is not the nearest direction when norms differ (normalising first picks train 0 here)."""
    query = np.zeros((1, 128), np.float32)
    query[0, 0] = 10
    train = np.zeros((2, 128), np.float32)
    train[0, 0] = 20  # same direction, 10 away
    train[1, 0], train[1, 1] = 10, 3  # another direction, 3 away
    expected = opencv_knn_ratio(query, train, cv2.NORM_L2)
    assert expected == [(0, 1)]
    assert repository_matches("sift-nn", query, train) == expected
    rng = np.random.default_rng(3)
    # Whole numbers up to 255 with uneven norms, as OpenCV's SIFT descriptors are.
    random0 = np.floor(rng.random((300, 128)) ** 3 * 256).astype(np.float32)
    random1 = np.clip(random0[rng.permutation(300)[:250]] + rng.integers(-20, 21, (250, 128)), 0, 255)
    random1 = random1.astype(np.float32)
    expected = opencv_knn_ratio(random0, random1, cv2.NORM_L2)
    assert len(expected) > 50
    assert repository_matches("sift-nn", random0, random1) == expected


def test_repository_sift_float32_product_equals_opencv_where_roots_tie():
    """Whole SIFT-like descriptors take the float32 product (``exact_in_float32``); the nearest
    comes from the product and only two roots a row are taken. OpenCV roots every distance in
    float32, where two squared distances can round to one root: there the nearest is a tie, the
    ratio test fails, and both drop the row."""
    from gvbench_nb.protocol.matching.nearest_neighbour import exact_in_float32

    rng = np.random.default_rng(11)
    # OpenCV's SIFT descriptors: whole numbers, norm about 512.
    random0 = rng.random((300, 128)) ** 3
    random0 = np.round(random0 / np.linalg.norm(random0, axis=1, keepdims=True) * 512).astype(np.float32)
    random1 = np.clip(random0[rng.permutation(300)[:250]] + rng.integers(-30, 31, (250, 128)), 0, 255)
    random1 = random1.astype(np.float32)
    assert exact_in_float32(random0) and exact_in_float32(random1)
    expected = opencv_knn_ratio(random0, random1, cv2.NORM_L2)
    assert len(expected) > 50
    assert repository_matches("sift-nn", random0, random1) == expected

    # Two train descriptors at squared distances 2^22 + m and 2^22 + m + 1 from the query, whose
    # float32 roots are equal (m found below): OpenCV sees a tie, the product a nearest.
    m = next(
        m for m in range(4_000_000, 4_190_000) if np.sqrt(np.float32(4194304 + m)) == np.sqrt(np.float32(4194305 + m))
    )
    query = np.zeros((1, 128), np.float32)
    query[0, 0] = 2048  # squared norm 2^22, orthogonal to both train descriptors

    def with_squared_norm(target: int, first: int = 1) -> np.ndarray:
        row, left, slot = np.zeros(128, np.float32), target, first
        while left:  # whole components, largest first, whose squares add up to the target
            row[slot] = math.isqrt(left)
            left -= int(row[slot]) ** 2
            slot += 1
        return row

    far = np.zeros(128, np.float32)
    far[100] = 2048  # 2^23 away: farther than both
    train = np.stack([with_squared_norm(m + 1), with_squared_norm(m), far])
    assert exact_in_float32(query) and exact_in_float32(train)
    pairs = cv2.BFMatcher(cv2.NORM_L2).knnMatch(query, train, k=2)
    assert pairs[0][0].distance == pairs[0][1].distance  # the tie OpenCV sees
    assert repository_matches("sift-nn", query, train) == opencv_knn_ratio(query, train, cv2.NORM_L2) == []
    # Squared distances 27 and 48: the roots' ratio is 0.75 exactly, but in float32 the first is
    # below 0.75 times the second (float64 roots would drop the match): OpenCV keeps it, and so do we.
    assert np.sqrt(np.float32(27)) < 0.75 * np.float64(np.sqrt(np.float32(48))) and not np.sqrt(27) < 0.75 * np.sqrt(48)
    origin, ratio_edge = np.zeros((1, 128), np.float32), np.stack([with_squared_norm(27), with_squared_norm(48)])
    assert repository_matches("sift-nn", origin, ratio_edge) == opencv_knn_ratio(origin, ratio_edge, cv2.NORM_L2)
    assert opencv_knn_ratio(origin, ratio_edge, cv2.NORM_L2) == [(0, 0)]
    near = query[0].copy()
    near[0] = 2047  # 1 away: a clear nearest, both keep it
    close = np.stack([train[0], train[1], near])
    assert repository_matches("sift-nn", query, close) == opencv_knn_ratio(query, close, cv2.NORM_L2) == [(0, 2)]


@pytest.mark.shared_outputs  # renders params/sample.yaml's images into outputs/sample
@pytest.mark.slow
@pytest.mark.reliability
def test_a_run_of_another_profile_prints_its_own_table_and_names_the_rows_of_the_other_run(tmp_path, capsys):
    from gvbench_nb import cli
    from gvbench_nb.runner import runs

    out = tmp_path / "out"
    common = ["run", "params/sample.yaml", "--limit", "4", "--output-dir", str(out)]
    assert cli.main([*common, "--methods", "orb-nn,sift-nn"]) == 0
    assert "not in this table" not in capsys.readouterr().err
    assert cli.main([*common, "--methods", "orb-nn", "--profile", "paper"]) == 0
    said = capsys.readouterr()
    (first, _), (second, _) = runs.finished_runs(out)
    assert [line.split()[:2] for line in said.out.splitlines() if line.startswith(("orb-nn", "sift-nn"))] == [
        ["orb-nn", "paper"]
    ]  # the run's own table; the folder's shows every recipe a row, and says so
    (line,) = [line for line in said.out.splitlines() if line.startswith(f"{out} shows also ")]
    assert f"of run {first.name}" in line and "orb-nn (repository profile)" in line and "sift-nn" in line
    assert "not in this table" not in said.err


def pil_bilinear(channel: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """PIL's BILINEAR on a float channel: the algorithm of torchvision's Resize(antialias=True)."""
    return np.asarray(Image.fromarray(channel.astype(np.float32), mode="F").resize(size, Image.BILINEAR))


def test_repository_lightglue_image_is_the_forks_float_chain_rounded_once(tmp_path):
    """The fork's base_matcher.py:L47-49 (ToTensor of PIL's RGB, Resize((288, 512),
    antialias=True)), then cvg/LightGlue's extractor input (utils.py ImagePreprocessor, resize
    1024 on the long side, bilinear): all in float. Ours is that image made 8-bit once, at
    the end: within half a grey level of it everywhere."""
    rng = np.random.default_rng(7)
    rgb = cv2.resize(rng.random((30, 50, 3)).astype(np.float32), (960, 540), interpolation=cv2.INTER_CUBIC)
    rgb = (np.clip(rgb + 0.2 * rng.random((540, 960, 3)), 0, 1) * 255).astype(np.uint8)
    path = tmp_path / "frame.png"
    Image.fromarray(rgb).save(path)
    unit = rgb.astype(np.float32) / 255
    theirs = np.stack([pil_bilinear(pil_bilinear(unit[..., c], (512, 288)), (1024, 576)) for c in range(3)], axis=-1)
    ours, _ = images.load_for_extraction(path, methods.resolve_method("disk-lg", "repository")["extractor"])
    assert ours.shape == (576, 1024, 3) and np.array_equal(ours, np.round(ours))
    assert np.abs(ours - theirs * 255).max() <= 0.5 + 1e-2


def test_repository_loftr_image_is_the_forks_grey_512x288(tmp_path):
    """The fork's loftr.py:L13 tfm.Grayscale (0.2989 R + 0.587 G + 0.114 B) of the resized
    512x288 image (base_matcher.py:L49), no further resize; ours within half a grey level
    plus OpenCV's grey weights (0.299, 0.587, 0.114: at most 0.03 levels apart)."""
    rng = np.random.default_rng(8)
    rgb = (rng.random((540, 960, 3)) * 255).astype(np.uint8)
    path = tmp_path / "frame.png"
    Image.fromarray(rgb).save(path)
    resized = np.stack([pil_bilinear(rgb[..., c] / np.float32(255), (512, 288)) for c in range(3)], axis=-1)
    theirs = resized @ np.array([0.2989, 0.587, 0.114], np.float32) * 255
    ours, scale = images.load_for_extraction(path, methods.resolve_method("loftr", "repository")["matcher"])
    assert ours.shape == (288, 512)
    assert np.abs(ours - theirs).max() <= 0.5 + 0.03
    np.testing.assert_allclose(scale, [960 / 512, 540 / 288], rtol=1e-6)


def test_repository_ratio_test_keeps_no_match_against_a_single_descriptor():
    """The fork's handcrafted.py:L47 unpacks two neighbours a row (``for m, n in raw_matches``),
    which fails when the other image has one descriptor; we keep no match there. A single
    descriptor on the query side has two neighbours and matches as the fork's loop does."""
    rng = np.random.default_rng(9)
    many = np.floor(rng.random((30, 128)) * 100).astype(np.float32)
    one = many[:1] + 1
    assert len(cv2.BFMatcher(cv2.NORM_L2).knnMatch(many, one, k=2)[0]) == 1  # one neighbour only
    assert repository_matches("sift-nn", many, one) == []
    expected = opencv_knn_ratio(one, many, cv2.NORM_L2)
    assert expected == [(0, 0)] and repository_matches("sift-nn", one, many) == expected
