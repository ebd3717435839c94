"""Reading images of any common kind and resizing them as the paper's protocol says."""

from __future__ import annotations

import os
from pathlib import Path

import cv2
import numpy as np


class ImageReadError(OSError):
    """An image is missing, empty, truncated or not an image."""


_REPLACE_HINT = "copy the file again from its source, or remove the pairs that use it from the pair file"


def read_image(path: str | os.PathLike[str], grayscale: bool = False) -> np.ndarray:
    """Read an image as uint8 RGB (H, W, 3) or gray (H, W).

    16-bit, RGBA, palette and grayscale files are converted rather than rejected;
    missing, empty and undecodable files raise ``ImageReadError`` naming the file.
    """
    path = Path(path)
    if not path.is_file():
        what = "is a folder, not an image file" if path.is_dir() else "not found"
        raise ImageReadError(f"image {what}: {path}; check image_root and the pair file's paths")
    try:
        data = np.fromfile(path, dtype=np.uint8)
    except OSError as error:
        raise ImageReadError(f"cannot read image {path}: {error.strerror or error}") from error
    if data.size == 0:
        raise ImageReadError(f"image file is empty (0 bytes): {path}; {_REPLACE_HINT}")
    # OpenCV returns None for truncated JPEG and PNG data rather than a grey-filled image
    # (tests/test_reliability.py checks it); the first bytes show what the file really is.
    image = cv2.imdecode(data, cv2.IMREAD_UNCHANGED)
    if image is None or image.size == 0:
        raise ImageReadError(
            f"cannot decode image {path} ({data.size} bytes, starting {bytes(data[:8])!r}): "
            f"not an image, or truncated; {_REPLACE_HINT}"
        )
    if image.dtype == np.uint16:
        image = (image.astype(np.float32) / 257.0).round().astype(np.uint8)
    elif image.dtype != np.uint8:
        scale = 255.0 if image.dtype.kind == "f" and image.max() <= 1.0 else 1.0
        image = np.clip(image.astype(np.float32) * scale, 0, 255).astype(np.uint8)
    if image.ndim == 2:
        return image if grayscale else cv2.cvtColor(image, cv2.COLOR_GRAY2RGB)
    if image.shape[2] == 4:
        image = cv2.cvtColor(image, cv2.COLOR_BGRA2BGR)
    if grayscale:
        return cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    return cv2.cvtColor(image, cv2.COLOR_BGR2RGB)


def target_size(width: int, height: int, resize_max: int | None, resize_force: bool = False,
                multiple_of: int | None = None, resize_to: tuple[int, int] | None = None) -> tuple[int, int]:
    """(width, height) after resizing the longest side to ``resize_max``.

    Without ``resize_force`` images are only shrunk (hloc's convention); with it they
    are also enlarged (the paper's SuperPoint at 1600). ``multiple_of`` floors both
    sides (LoFTR's multiple of 8). ``resize_to`` = (width, height) is a fixed size
    whatever the aspect ratio (the GV-Bench repository's 512x288); it replaces ``resize_max``.
    """
    new_w, new_h = width, height
    if resize_to:
        new_w, new_h = int(resize_to[0]), int(resize_to[1])
    elif resize_max and (resize_force or max(width, height) > resize_max):
        scale = resize_max / max(width, height)
        new_w, new_h = int(round(width * scale)), int(round(height * scale))
    if multiple_of:
        new_w, new_h = new_w // multiple_of * multiple_of, new_h // multiple_of * multiple_of
    return new_w, new_h


def resize_image(image: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """Resize to (width, height): INTER_AREA when shrinking, INTER_LINEAR when enlarging."""
    height, width = image.shape[:2]
    if (width, height) == tuple(size):
        return image
    shrinking = size[0] * size[1] < width * height
    return cv2.resize(image, size, interpolation=cv2.INTER_AREA if shrinking else cv2.INTER_LINEAR)


def resize_bilinear_antialias(image: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """Resize a float image to (width, height) as torchvision's ``Resize(antialias=True)`` does
    on a tensor (bilinear, half-pixel centres, antialiased when shrinking); stays float32."""
    import torch

    height, width = image.shape[:2]
    if (width, height) == tuple(size):
        return image.astype(np.float32)
    tensor = torch.from_numpy(np.ascontiguousarray(image, dtype=np.float32))
    tensor = tensor[None, None] if tensor.ndim == 2 else tensor.permute(2, 0, 1)[None]
    resized = torch.nn.functional.interpolate(tensor, size=(int(size[1]), int(size[0])), mode="bilinear",
                                              align_corners=False, antialias=True)[0]
    return (resized[0] if image.ndim == 2 else resized.permute(1, 2, 0)).numpy()


def _prepare_as_repository(path: str | os.PathLike[str], conf: dict) -> tuple[np.ndarray, tuple[int, int]]:
    """The GV-Bench repository's image chain: RGB in [0, 1], resized as a float image, then
    grey (its OpenCV and LoFTR matchers convert after resizing), min-max stretched to 0-255
    where its OpenCV matchers do, and resized again when the model resizes its input
    (LightGlue's extractors: longest side ``model_input_long_side``, also enlarging).
    Rounded to 8 bits once, at the end. Returns the image and the original (width, height)."""
    rgb = read_image(path, grayscale=False).astype(np.float32)
    height, width = rgb.shape[:2]
    fixed = conf.get("resize_to")
    size = (int(fixed[0]), int(fixed[1])) if fixed else target_size(width, height, conf.get("resize_max"),
                                                                    conf.get("resize_force", False))
    image = resize_bilinear_antialias(rgb, size)
    if conf.get("grayscale", False):
        image = cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)
    if conf.get("normalize_minmax", False):
        image = cv2.normalize(image, None, 0, 255, cv2.NORM_MINMAX)
    long_side = conf.get("model_input_long_side")
    if long_side:
        scale = long_side / max(image.shape[:2])
        image = resize_bilinear_antialias(image, (int(image.shape[1] * scale), int(image.shape[0] * scale)))
    multiple_of = conf.get("multiple_of")
    if multiple_of:
        h, w = image.shape[:2]
        image = resize_bilinear_antialias(image, (w // multiple_of * multiple_of, h // multiple_of * multiple_of))
    return np.clip(np.round(image), 0, 255).astype(np.uint8), (width, height)


def load_for_extraction(path: str | os.PathLike[str], conf: dict) -> tuple[np.ndarray, np.ndarray]:
    """Image prepared for an extractor conf, and the (sx, sy) scale back to original pixels.

    ``interpolation``: "area_or_linear" (default; hloc's rule) or "bilinear_antialias"
    (the GV-Bench repository's torchvision chain, ``_prepare_as_repository``).
    """
    interpolation = conf.get("interpolation", "area_or_linear")
    if interpolation == "bilinear_antialias":
        resized, (width, height) = _prepare_as_repository(path, conf)
        size = resized.shape[1::-1]
    elif interpolation == "area_or_linear":
        image = read_image(path, grayscale=conf.get("grayscale", False))
        height, width = image.shape[:2]
        size = target_size(width, height, conf.get("resize_max"), conf.get("resize_force", False),
                           conf.get("multiple_of"), conf.get("resize_to"))
        resized = resize_image(image, size)
    else:
        raise ValueError(f"unknown interpolation {interpolation!r} in the conf of {conf.get('name', '?')!r}; "
                         "use 'area_or_linear' or 'bilinear_antialias'")
    scale = np.array([width / size[0], height / size[1]], dtype=np.float64)
    return resized, scale


def to_original_pixels(keypoints: np.ndarray, scale: np.ndarray) -> np.ndarray:
    """Map keypoints of the resized image back with (k + 0.5) * scale - 0.5 (pixel centres)."""
    return ((keypoints + 0.5) * scale - 0.5).astype(np.float32)
