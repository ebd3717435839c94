"""Reading images of any common kind and resizing them as the paper's protocol says."""

from __future__ import annotations

import errno
import os
import stat
from pathlib import Path

import cv2
import numpy as np

from gvbench_nb import GVBenchError
from gvbench_nb.protocol import registry

# The image files a folder of images is read for (what OpenCV decodes here).
IMAGE_EXTENSIONS = (".jpg", ".jpeg", ".png", ".ppm", ".bmp")


# What keeps a path from being read as a file: by the errno of its stat, then by its kind.
_STAT_ERRORS = {
    errno.ELOOP: "is a symbolic link loop (following it leads back to itself)",
    errno.ENOENT: "does not exist",
    errno.ENOTDIR: "does not exist (a folder on its path is a file)",
    errno.EACCES: "cannot be reached (permission denied on a folder of its path)",
    errno.ENAMETOOLONG: "has a name longer than the file system allows",
}
_NOT_FILES = (
    (stat.S_ISDIR, "is a folder, not a file"),
    (stat.S_ISFIFO, "is a FIFO (named pipe), not a file"),
    (stat.S_ISCHR, "is a device, not a file"),
    (stat.S_ISBLK, "is a device, not a file"),
    (stat.S_ISSOCK, "is a socket, not a file"),
)


def path_problem(path: str | os.PathLike[str]) -> str | None:
    """What keeps ``path`` from being read as a regular file, in words following its name, or
    None; reads metadata only (a FIFO is named, never opened: opening one blocks)."""
    text = os.fspath(path)
    if "\0" in text:
        return "holds a NUL byte, which no file name can"
    try:
        mode = os.stat(text).st_mode
    except OSError as error:
        if error.errno == errno.ENOENT and os.path.islink(text):
            return f"is a broken symbolic link (to {os.readlink(text)}, which does not exist)"
        return _STAT_ERRORS.get(error.errno or 0, f"cannot be used ({error.strerror or error})")
    if stat.S_ISREG(mode):
        return None if os.access(text, os.R_OK) else "cannot be read (permission denied)"
    return next((problem for is_kind, problem in _NOT_FILES if is_kind(mode)), "is not a regular file")


class ImageReadError(GVBenchError, OSError):
    """An image is missing, empty, truncated or not an image."""


_REPLACE_HINT = "copy the file again from its source, or remove the pairs that use it from the pair file"

# Images above this many pixels are refused before decoding (a 20000 x 20000 PNG of 1 MB
# decodes to gigabytes). 64 MP is over 50 times a GV-Bench frame and above most cameras;
# $GVBENCH_MAX_PIXELS raises or lowers it.
DEFAULT_MAX_PIXELS = 64_000_000


def max_pixels() -> int:
    """The pixel bound: $GVBENCH_MAX_PIXELS, else ``DEFAULT_MAX_PIXELS``."""
    value = os.environ.get("GVBENCH_MAX_PIXELS")
    if not value:
        return DEFAULT_MAX_PIXELS
    if not value.isdigit() or int(value) < 1:
        raise ImageReadError(
            f"GVBENCH_MAX_PIXELS must be a positive whole number of pixels, got {value!r}; fix or unset it"
        )
    return int(value)


def check_pixel_bound(path: str | os.PathLike[str]) -> None:
    """Refuse an image whose header says it is larger than ``max_pixels()``, without decoding it."""
    import re

    from PIL import Image

    bound = max_pixels()
    try:
        with Image.open(path) as image:  # lazy: the pixels are not read
            width, height = image.size
            size, pixels = f"is {width} x {height} = {width * height:,} pixels", width * height
    except Image.DecompressionBombError as error:  # Pillow's own limit, far above ours; it says the count
        found = re.search(r"\((\d+) pixels\)", str(error))
        pixels = int(found.group(1)) if found else bound + 1
        size = f"has {pixels:,} pixels" if found else "is larger than Pillow opens"
    except Exception:  # not a format Pillow knows (or damaged): the decoder reports it
        return
    if pixels > bound:
        raise ImageReadError(
            f"image {path} {size}, above the bound of {bound:,} pixels (refused before decoding); "
            "shrink it, or raise the bound with GVBENCH_MAX_PIXELS"
        )


# A run refuses images with a side under this many pixels before any work: some extractors fail
# on them (OpenCV's ORB on a 1 x 1 image, DISK under the paper's profile on a 16 x 16 one).
MIN_SIDE = 32


def check_min_side(path: str | os.PathLike[str]) -> None:
    """Refuse an image whose header says a side is under ``MIN_SIDE`` pixels (one Pillow cannot
    open is left to the decoder)."""
    from PIL import Image

    try:
        with Image.open(path) as image:  # lazy: the pixels are not read
            width, height = image.size
    except Exception:
        return
    if min(width, height) < MIN_SIDE:
        raise ImageReadError(
            f"image {path} is {width} x {height} pixels, too small to verify (the extractors need at least "
            f"{MIN_SIDE} pixels a side); replace it, or remove the pairs that use it from the pair file"
        )


def read_image(path: str | os.PathLike[str], grayscale: bool = False, exif_orientation: bool = False) -> np.ndarray:
    """Read an image as uint8 RGB (H, W, 3) or gray (H, W); odd formats are converted, bad files
    raise ``ImageReadError``. ``exif_orientation``: turn it as hloc's ``cv2.imread`` does (the
    GV-Bench repository's PIL loader does not, nor does this by default)."""
    path = Path(path)
    problem = path_problem(path)
    if problem == "does not exist":
        raise ImageReadError(f"image not found: {path}; check image_root and the pair file's paths")
    if problem is not None:
        raise ImageReadError(f"image {path} {problem}; check image_root and the pair file's paths")
    check_pixel_bound(path)
    try:
        data = np.fromfile(path, dtype=np.uint8)
    except OSError as error:
        raise ImageReadError(f"cannot read image {path}: {error.strerror or error}") from error
    if data.size == 0:
        raise ImageReadError(f"image file is empty (0 bytes): {path}; {_REPLACE_HINT}")
    # OpenCV returns None for truncated JPEG and PNG data rather than a grey-filled image
    # (tests/runner/test_reliability.py checks it); the first bytes show what the file really is.
    # Grayscale is decoded as grayscale (hloc's cv2.IMREAD_GRAYSCALE: a JPEG's luma as
    # libjpeg computes it, which a cvtColor of the colour image misses by up to 2 levels);
    # ANYDEPTH keeps 16-bit files 16-bit for the conversion below. OpenCV turns the image by
    # its EXIF orientation unless told not to; IMREAD_UNCHANGED never does.
    if grayscale:
        flags = cv2.IMREAD_GRAYSCALE | cv2.IMREAD_ANYDEPTH
        if not exif_orientation:
            flags |= cv2.IMREAD_IGNORE_ORIENTATION
    else:
        flags = cv2.IMREAD_COLOR | cv2.IMREAD_ANYDEPTH if exif_orientation else cv2.IMREAD_UNCHANGED
    image = cv2.imdecode(data, flags)
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


def target_size(
    width: int,
    height: int,
    resize_max: int | None,
    resize_force: bool = False,
    multiple_of: int | None = None,
    resize_to: tuple[int, int] | None = None,
) -> tuple[int, int]:
    """(width, height) after resizing the longest side to ``resize_max``: only shrinking (hloc)
    unless ``resize_force``; ``multiple_of`` floors both sides (LoFTR's 8); ``resize_to`` is a
    fixed (width, height) replacing ``resize_max`` (the GV-Bench repository's 512x288)."""
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
    """Resize to (width, height) as hloc's ``extract_features.resize_image`` with cv2_area:
    INTER_AREA, or INTER_LINEAR when either side grows."""
    height, width = image.shape[:2]
    if (width, height) == tuple(size):
        return image
    enlarging = size[0] > width or size[1] > height
    return cv2.resize(image, tuple(size), interpolation=cv2.INTER_LINEAR if enlarging else cv2.INTER_AREA)


def resize_bilinear_antialias(image: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """Resize a float image to (width, height) as torchvision's ``Resize(antialias=True)`` does
    on a tensor (bilinear, half-pixel centres, antialiased when shrinking); stays float32."""
    import torch

    height, width = image.shape[:2]
    if (width, height) == tuple(size):
        return image.astype(np.float32)
    tensor = torch.from_numpy(np.ascontiguousarray(image, dtype=np.float32))
    tensor = tensor[None, None] if tensor.ndim == 2 else tensor.permute(2, 0, 1)[None]
    resized = torch.nn.functional.interpolate(
        tensor, size=(int(size[1]), int(size[0])), mode="bilinear", align_corners=False, antialias=True
    )[0]
    return (resized[0] if image.ndim == 2 else resized.permute(1, 2, 0)).numpy()


def _prepare_as_repository(path: str | os.PathLike[str], conf: dict) -> tuple[np.ndarray, tuple[int, int]]:
    """The GV-Bench repository's image chain: RGB [0, 1] resized as float, grey after resizing,
    min-max stretched for its OpenCV matchers, resized again for LightGlue's extractors, made 8-bit
    once at the end (rounded, or truncated per the conf's ``uint8``). Returns image, (w, h)."""
    stretched = conf.get("normalize_minmax", False)
    rgb = read_image(path, grayscale=False).astype(np.float32)
    if stretched:
        # The stretch's input as the fork has it, torchvision's ToTensor (x / 255 in float32):
        # the grey conversion and min-max scaling then round as there, which truncation exposes.
        rgb /= np.float32(255.0)
    height, width = rgb.shape[:2]
    size = target_size(
        width, height, conf.get("resize_max"), conf.get("resize_force", False), resize_to=conf.get("resize_to")
    )
    image = resize_bilinear_antialias(rgb, size)
    if conf.get("grayscale", False):
        image = cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)
    if stretched:
        # OpenCV's stubs omit that dst may be None (a new array of src's type).
        image = cv2.normalize(image, None, 0, 255, cv2.NORM_MINMAX)  # type: ignore[call-overload]
    long_side = conf.get("model_input_long_side")
    if long_side:
        scale = long_side / max(image.shape[:2])
        image = resize_bilinear_antialias(image, (int(image.shape[1] * scale), int(image.shape[0] * scale)))
    multiple_of = conf.get("multiple_of")
    if multiple_of:
        h, w = image.shape[:2]
        image = resize_bilinear_antialias(image, (w // multiple_of * multiple_of, h // multiple_of * multiple_of))
    conversion = conf.get("uint8", "round")
    registry.check_choice("uint8", conversion, ("round", "truncate"), f"the conf of {conf.get('name', '?')!r}")
    image = np.clip(image, 0, 255)
    return (np.floor(image) if conversion == "truncate" else np.round(image)).astype(np.uint8), (width, height)


def load_for_extraction(path: str | os.PathLike[str], conf: dict) -> tuple[np.ndarray, np.ndarray]:
    """Image prepared for an extractor conf (float32, 0..255) and the (sx, sy) scale back to the
    original; ``interpolation`` "area_or_linear" is hloc's ``ImageDataset`` (resized as float32),
    "bilinear_antialias" the GV-Bench repository's torchvision chain."""
    interpolation = conf.get("interpolation", "area_or_linear")
    where = f"the conf of {conf.get('name', '?')!r}"
    registry.check_choice("interpolation", interpolation, ("area_or_linear", "bilinear_antialias"), where)
    if interpolation == "bilinear_antialias":
        resized8, (width, height) = _prepare_as_repository(path, conf)
        resized = resized8.astype(np.float32)
        size = resized.shape[1::-1]
    else:
        # hloc's read_image (cv2.imread) applies EXIF orientation.
        image = read_image(path, grayscale=conf.get("grayscale", False), exif_orientation=True).astype(np.float32)
        height, width = image.shape[:2]
        # "bilinear": hloc's match_dense floors each side to the multiple in a second resize
        # (torchvision's bilinear resize of the [0, 1] tensor) after the INTER_AREA shrink;
        # otherwise the floored size is reached in the one resize.
        floor_separately = conf.get("multiple_of_resize") == "bilinear" and conf.get("multiple_of")
        size = target_size(
            width,
            height,
            conf.get("resize_max"),
            conf.get("resize_force", False),
            None if floor_separately else conf.get("multiple_of"),
            conf.get("resize_to"),
        )
        resized = resize_image(image, size)
        if floor_separately:
            multiple = int(conf["multiple_of"])
            size = (size[0] // multiple * multiple, size[1] // multiple * multiple)
            unit = resize_bilinear_antialias(resized / np.float32(255.0), size)
            resized = unit * np.float32(255.0)
    scale = (np.array([width, height]) / np.array(size)).astype(np.float32)
    return resized, scale


def to_original_pixels(keypoints: np.ndarray, scale: np.ndarray) -> np.ndarray:
    """Map keypoints of the resized image back with (k + 0.5) * scale - 0.5 (pixel centres),
    in float32 as hloc computes it."""
    keypoints = np.asarray(keypoints, dtype=np.float32)
    return ((keypoints + np.float32(0.5)) * np.asarray(scale, dtype=np.float32) - np.float32(0.5)).astype(np.float32)
