"""Image reading, resizing, COLMAP SIFT and float16 storage against references written from hloc's
code (``utils/io.py``, ``extract_features.py``, ``extractors/dog.py``) where readings differ."""

from __future__ import annotations

import warnings
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from gvbench_nb import methods
from gvbench_nb.data.sequences import Pair, Sequence
from gvbench_nb.protocol import features as extractors
from gvbench_nb.protocol import images
from gvbench_nb.runner import image_features, method_runs, pair_matching

GARDENS_POINT_IMAGES = [
    "night_right/Image050.jpg",
    "day_right/Image050.jpg",
    "day_right/Image120.jpg",
    "night_right/Image180.jpg",
]


def _textured(height: int, width: int, seed: int = 0) -> np.ndarray:
    """A smooth colour texture with blobs and edges: SIFT finds hundreds of keypoints on it."""
    rng = np.random.default_rng(seed)
    noise = rng.random((height // 8 + 1, width // 8 + 1, 3)).astype(np.float32)
    image = cv2.resize(noise, (width, height), interpolation=cv2.INTER_CUBIC)
    for _ in range(40):
        centre = (int(rng.integers(0, width)), int(rng.integers(0, height)))
        cv2.circle(image, centre, int(rng.integers(3, 25)), tuple(float(v) for v in rng.random(3)), -1)
    return np.clip(image * 255, 0, 255).astype(np.uint8)


def hloc_prepare(
    path: Path, grayscale: bool, resize_max: int | None, resize_force: bool = False
) -> tuple[np.ndarray, np.ndarray]:
    """hloc's ImageDataset: cv2.imread (grayscale or colour, EXIF orientation ignored),
    float32, and when the longest side exceeds resize_max (or always, forced) a resize to
    int(round(side * resize_max / longest)), cv2 INTER_AREA unless a side grows (then
    INTER_LINEAR). Returns the image in 0..255 and original / new size as float32."""
    mode = cv2.IMREAD_GRAYSCALE if grayscale else cv2.IMREAD_COLOR
    image = cv2.imread(str(path), mode | cv2.IMREAD_IGNORE_ORIENTATION)
    if not grayscale:
        image = image[:, :, ::-1]
    image = image.astype(np.float32)
    original = np.array(image.shape[:2][::-1])
    size = original
    if resize_max and (resize_force or original.max() > resize_max):
        factor = resize_max / original.max()
        size = np.array([int(round(side * factor)) for side in original])
        grows = size[0] > original[0] or size[1] > original[1]
        image = cv2.resize(
            image, (int(size[0]), int(size[1])), interpolation=cv2.INTER_LINEAR if grows else cv2.INTER_AREA
        )
    return image, (original / size).astype(np.float32)


def hloc_dog(image: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """hloc's `dog` extractor with its `sift` conf, on pycolmap directly: first octave 0,
    peak threshold 0.01, L1_ROOT normalisation, pycolmap's default feature cap; the image
    in [0, 1]; x, y kept, zero scores, descriptors renormalised by hloc's RootSIFT step."""
    import pycolmap

    options = pycolmap.SiftExtractionOptions()
    options.first_octave, options.peak_threshold = 0, 0.01
    options.normalization = pycolmap.Normalization.L1_ROOT
    with warnings.catch_warnings():  # hloc's own call, which pycolmap 4 deprecates
        warnings.simplefilter("ignore", DeprecationWarning)
        sift = pycolmap.Sift(options=pycolmap.FeatureExtractionOptions(sift=options), device=pycolmap.Device.cpu)
    keypoints, descriptors = sift.extract(np.ascontiguousarray(image / 255.0, dtype=np.float32))
    eps = 1e-6
    descriptors = descriptors / (np.linalg.norm(descriptors, ord=1, axis=-1, keepdims=True) + eps)
    descriptors = np.sqrt(descriptors.clip(min=eps))
    descriptors = descriptors / (np.linalg.norm(descriptors, axis=-1, keepdims=True) + eps)
    return keypoints[:, :2], np.zeros(len(keypoints), np.float32), descriptors


# ------------------------------------------------------------------ reading --
def test_grayscale_is_decoded_as_grayscale_not_converted_from_colour(tmp_path):
    path = tmp_path / "colour.jpg"
    cv2.imwrite(str(path), _textured(120, 160), [cv2.IMWRITE_JPEG_QUALITY, 90])
    ours = images.read_image(path, grayscale=True)
    expected = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE | cv2.IMREAD_IGNORE_ORIENTATION)
    converted = cv2.cvtColor(cv2.imread(str(path)), cv2.COLOR_BGR2GRAY)
    assert np.any(expected != converted)  # the case tells the two readings apart
    np.testing.assert_array_equal(ours, expected)


# ----------------------------------------------------------------- resizing --
@pytest.mark.parametrize("size", [(150, 50), (60, 40), (100, 130), (100, 100)])
def test_resize_interpolation_follows_hloc_which_side_decides(size):
    image = _textured(100, 100).astype(np.float32)
    grows = size[0] > 100 or size[1] > 100  # 150x50: linear although its area shrinks
    expected = cv2.resize(image, size, interpolation=cv2.INTER_LINEAR if grows else cv2.INTER_AREA)
    other = cv2.resize(image, size, interpolation=cv2.INTER_AREA if grows else cv2.INTER_LINEAR)
    assert size == (100, 100) or not np.array_equal(expected, other)  # the case tells them apart
    np.testing.assert_array_equal(images.resize_image(image, size), expected)


@pytest.mark.parametrize(
    "grayscale, resize_max, force",
    [(True, 1600, False), (False, 1600, False), (True, 333, False), (True, 1600, True), (False, 512, True)],
)
def test_load_for_extraction_equals_hloc_preparation(tmp_path, grayscale, resize_max, force):
    path = tmp_path / "image.jpg"
    cv2.imwrite(str(path), _textured(375, 500), [cv2.IMWRITE_JPEG_QUALITY, 92])
    conf = {"grayscale": grayscale, "resize_max": resize_max, "resize_force": force}
    image, scale = images.load_for_extraction(path, conf)
    expected, expected_scale = hloc_prepare(path, grayscale, resize_max, force)
    assert image.dtype == np.float32 and scale.dtype == np.float32
    np.testing.assert_array_equal(image, expected)
    np.testing.assert_array_equal(scale, expected_scale)
    if resize_max == 333:  # resized as float: values between grey levels survive
        assert np.any(image != np.round(image))


def test_keypoints_map_back_through_pixel_centres_in_float32():
    keypoints = np.array([[0.0, 0.0], [10.25, 3.5], [332.0, 249.0]], np.float32)
    scale = (np.array([500, 375]) / np.array([333, 250])).astype(np.float32)
    expected = (keypoints + 0.5) * scale[None] - 0.5  # float32 throughout, as hloc computes it
    np.testing.assert_array_equal(images.to_original_pixels(keypoints, scale), expected)
    assert images.to_original_pixels(keypoints, scale).dtype == np.float32


def test_disk_is_shrunk_to_1600_and_never_enlarged(tmp_path):
    conf = methods.resolve_method("disk-nn", "paper")["extractor"]
    assert conf["resize_max"] == 1600 and not conf["resize_force"]
    large, small = tmp_path / "large.png", tmp_path / "small.png"
    cv2.imwrite(str(large), _textured(900, 2000))
    cv2.imwrite(str(small), _textured(300, 400))
    assert images.load_for_extraction(large, conf)[0].shape == (720, 1600, 3)
    assert images.load_for_extraction(small, conf)[0].shape == (300, 400, 3)


# ------------------------------------------------------------- COLMAP SIFT --
def test_sift_is_colmap_sift_with_hloc_conf(tmp_path):
    path = tmp_path / "image.png"
    cv2.imwrite(str(path), _textured(480, 640, seed=4))
    conf = methods.resolve_method("sift-nn", "paper")["extractor"]
    image, _ = images.load_for_extraction(path, conf)
    ours = extractors.build_extractor(conf, torch.device("cpu"))(image)
    keypoints, scores, descriptors = hloc_dog(hloc_prepare(path, True, 1600)[0])
    assert len(keypoints) > 100
    np.testing.assert_array_equal(ours["keypoints"], keypoints)
    np.testing.assert_array_equal(ours["scores"], scores)
    np.testing.assert_allclose(ours["descriptors"], descriptors, rtol=0, atol=1e-7)
    # OpenCV's SIFT stays available under its own name, and is a different detector.
    opencv_conf = methods.resolve_method("sift-opencv-nn", "paper")["extractor"]
    opencv = extractors.build_extractor(opencv_conf, torch.device("cpu"))(image)
    assert opencv_conf["type"] == "opencv_sift" and len(opencv["keypoints"]) != len(keypoints)


def test_colmap_sift_passes_max_keypoints_to_pycolmap():
    # COLMAP keeps the coarsest scales, octave by octave, until it holds max_num_features
    # detections (finishing that octave; two orientations can share a position): a cap of 50
    # keeps a few dozen positions of the uncapped set.
    image = _textured(480, 640, seed=5)[..., 0].astype(np.float32)
    extractor = extractors.build_extractor(methods.RECIPES["paper"]["sift-nn"]["extractor"], torch.device("cpu"))
    uncapped = extractor(image)
    capped = extractors.build_extractor(
        {**methods.RECIPES["paper"]["sift-nn"]["extractor"], "max_keypoints": 50}, torch.device("cpu")
    )(image)
    all_positions = {tuple(p) for p in uncapped["keypoints"].tolist()}
    positions = {tuple(p) for p in capped["keypoints"].tolist()}
    assert positions <= all_positions and 50 <= len(positions) < len(all_positions) / 10
    with pytest.raises(ValueError, match="'grayscale': True"):  # a colour image: it says what to set
        extractor(image[..., None].repeat(3, 2))


# ---------------------------------------------------------- float16 storage --
def test_float16_storage_rounds_float_arrays_and_keeps_integers():
    rng = np.random.default_rng(0)
    features = {
        "keypoints": rng.random((20, 2), np.float32) * 1500,
        "scores": rng.random(20, np.float32),
        "descriptors": rng.random((20, 128), np.float32),
    }
    image, scale = np.zeros((540, 960), np.float32), np.ones(2, np.float32)
    stored = image_features.stored_features(features, image, scale, store_float16=True)
    for key in ("keypoints", "scores", "descriptors"):
        assert stored[key].dtype == np.float16
        np.testing.assert_array_equal(stored[key], features[key].astype(np.float16))
    assert stored["image_size"].dtype == np.int64
    binary = image_features.stored_features(
        {**features, "descriptors": rng.integers(0, 256, (20, 32), dtype=np.uint8)}, image, scale, store_float16=True
    )
    assert binary["descriptors"].dtype == np.uint8
    unrounded = image_features.stored_features(features, image, scale, store_float16=False)
    assert unrounded["keypoints"].dtype == np.float32


def test_store_float16_is_in_every_paper_extractor_conf_and_in_its_hash():
    for name, recipe in methods.RECIPES["paper"].items():
        assert recipe["extractor"] is None or recipe["extractor"]["store_float16"] is True, name
    conf = methods.resolve_method("sift-nn", "paper")["extractor"]
    assert methods.conf_hash(conf) != methods.conf_hash({**conf, "store_float16": False})


def test_matching_reads_the_float16_cache(tmp_path):
    root = tmp_path / "images"
    root.mkdir()
    for name, seed in (("a.png", 1), ("b.png", 1)):
        cv2.imwrite(str(root / name), _textured(240, 320, seed=seed))
    sequence = Sequence(name="tiny", image_root=root, pairs=[Pair("a.png", "b.png", 1)])
    conf = methods.resolve_method("sift-nn", "paper")
    image_features.extract_features(sequence, conf["extractor"], tmp_path / "cache", "cpu", progress=False)
    stored = image_features.feature_store(tmp_path / "cache", conf["extractor"]).read(
        image_features.image_key(root, "a.png")
    )
    assert stored["keypoints"].dtype == np.float16 and stored["descriptors"].dtype == np.float16
    pair_matching.match_and_verify(sequence, conf, tmp_path / "cache", "cpu", progress=False)
    table = method_runs.pairs_table(sequence, conf, tmp_path / "cache", seed=0)
    assert table["num_matches"][0] == len(stored["keypoints"])  # identical images match every keypoint


# ---------------------------------------------------------- real-data parity --
@pytest.mark.slow
@pytest.mark.real_data
def test_paper_sift_keypoint_counts_equal_pycolmap_with_hloc_settings_on_gardens_point(shared_data, tmp_path):
    root = shared_data / "gardens_point"
    pairs = [Pair(GARDENS_POINT_IMAGES[0], name, 0) for name in GARDENS_POINT_IMAGES[1:]]
    sequence = Sequence(name="gardens_point_parity", image_root=root, pairs=pairs)
    conf = methods.resolve_method("sift-nn", "paper")["extractor"]
    image_features.extract_features(sequence, conf, tmp_path / "cache", "cpu", progress=False)
    store = image_features.feature_store(tmp_path / "cache", conf)
    for name in GARDENS_POINT_IMAGES:
        ours = store.read(image_features.image_key(root, name))
        image, scale = hloc_prepare(root / name, True, 1600)
        keypoints, _, descriptors = hloc_dog(image)
        assert len(ours["keypoints"]) == len(keypoints), name
        expected = ((keypoints + 0.5) * scale - 0.5).astype(np.float16)
        np.testing.assert_array_equal(ours["keypoints"], expected)
        np.testing.assert_array_equal(ours["descriptors"], descriptors.astype(np.float16))
