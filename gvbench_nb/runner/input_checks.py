"""What a run needs, checked before it writes a file or imports a model: device, folders, weights,
builder options, the images (by content: a copy is one image, a damaged one is named) and recipes."""

from __future__ import annotations

import functools
import json
import os
import sys
import tempfile
import threading
from collections.abc import Callable
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from gvbench_nb import methods as method_registry
from gvbench_nb.data import build_inputs, sequences
from gvbench_nb.data.sequences import PairFileError, Sequence, frame_tolerance_pairs, pair_line_numbers, read_pairs
from gvbench_nb.io_utils import atomic_write_json, unknown_keys_hint
from gvbench_nb.protocol import metrics
from gvbench_nb.protocol.images import ImageReadError, check_min_side, path_problem
from gvbench_nb.runner import config, image_features, sequence_build


def _where(sequence: Sequence, index: int) -> str:
    """``pairs.txt:LINE`` of the sequence's pair ``index`` when its pair file holds it there, else the pair's index."""
    path = sequence.origin.get("pairs_file")
    try:
        if path and read_pairs(str(path))[index] == sequence.pairs[index]:
            return f"{path}:{pair_line_numbers(str(path))[index]}"
    except (OSError, PairFileError, IndexError):
        pass
    return f"{sequence.name}: pair {index}"


_decoder_lock = threading.Lock()


def decoder_message(path: str | os.PathLike[str]) -> str:
    """What the decoder says of an image ("" nothing): libjpeg/libpng warn on the process's stderr, caught
    there during an eighth-size grey decode (every byte still entropy-decoded). Raises ``ImageReadError``,
    also for an image with a side under ``MIN_SIDE`` pixels."""
    check_min_side(path)
    data = np.fromfile(path, dtype=np.uint8)
    with _decoder_lock, tempfile.TemporaryFile() as said:
        sys.stderr.flush()
        saved = os.dup(2)
        os.dup2(said.fileno(), 2)
        try:
            image = cv2.imdecode(data, cv2.IMREAD_REDUCED_GRAYSCALE_8) if data.size else None
        except cv2.error:  # OpenCV decodes it but cannot shrink it (a side under 8 pixels Pillow did not read)
            image = None
        finally:
            os.dup2(saved, 2)
            os.close(saved)
        said.seek(0)
        message = " ".join(said.read().decode(errors="replace").split())
    if image is None or image.size == 0:
        said_text = f"; the decoder said: {message}" if message else ""
        raise ImageReadError(
            f"cannot decode image {path} ({data.size} bytes, starting {bytes(data[:8])!r}): not an image, or "
            f"truncated{said_text}; copy the file again from its source, or remove the pairs that use it from the pair file"
        )
    return message


DECODER_CHECKS = "decoder-checks.json"  # in the cache folder: content key -> what its decoder said ("" nothing)
_decoded: dict[str, str] = {}  # this process's answers: kept once the cache folder exists (checks run before it does)


def decoder_messages(sequence: Sequence, keys: dict[str, str], cache_dir: Path) -> dict[str, str]:
    """Image name -> what its decoder said, when anything; each content decoded once, the answers kept
    in ``<cache_dir>/decoder-checks.json`` when that folder exists."""
    path = Path(cache_dir) / DECODER_CHECKS
    try:
        known = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        known = {}
    saved = known if isinstance(known, dict) else {}
    known = {**_decoded, **saved}
    unknown = {key: name for name, key in keys.items() if not isinstance(known.get(key), str)}
    unsaved = any(key not in saved for key in keys.values())
    for key, name in unknown.items():
        try:
            known[key] = decoder_message(Path(sequence.image_root) / name)
        except ImageReadError as error:
            raise ImageReadError(f"{error} ({image_features.first_pair_using(sequence, name)})") from None
    _decoded.update({key: known[key] for key in keys.values()})
    if unsaved and path.parent.is_dir():  # two runs at once: the later file wins, the other's images decode again
        atomic_write_json(path, {**saved, **{key: known[key] for key in keys.values()}})
    return {name: known[key] for name, key in keys.items() if known[key]}


def check_distinct_contents(
    sequence: Sequence, where: Callable[[int], str] | None = None, cache_dir: str | os.PathLike[str] | None = None
) -> dict[str, str]:
    """Refuse a pair of two images with one content (a copy or a link: a self-pair, as one named
    twice is), naming where the pair is (``where(index)``, else its pair file and line); returns the
    images' content keys (``image_features.image_keys``, kept in ``cache_dir``)."""
    keys = image_features.image_keys(sequence, cache_dir)
    for index, pair in enumerate(sequence.pairs):
        query, reference = keys[pair.query], keys[pair.reference]
        if query == reference:
            raise PairFileError(
                f"{(where or functools.partial(_where, sequence))(index)}: self-pair by content: {pair.query} and "
                f"{pair.reference} hold the same bytes (a copy of one image, or a link to it); a pair needs two "
                "different images, remove this line"
            )
    return keys


def check_image_contents(sequence: Sequence, cache_dir: str | os.PathLike[str], allow_damaged: bool) -> dict[str, str]:
    """Refuse a pair of two images with one content with file:line (``check_distinct_contents``), and an
    image whose decoder fails, or warns unless ``allow_damaged``. Returns the damaged images allowed
    (name -> what the decoder said), for the run's manifest."""
    keys = check_distinct_contents(sequence, cache_dir=cache_dir)
    damaged = decoder_messages(sequence, keys, Path(cache_dir))
    if damaged and not allow_damaged:
        name, said = next(iter(damaged.items()))
        raise ImageReadError(
            f"{len(damaged)} of {len(keys)} images of sequence {sequence.name!r} are damaged, first "
            f"{Path(sequence.image_root) / name} ({image_features.first_pair_using(sequence, name)}): its decoder "
            f"said {said!r}; replace it, remove the pairs that use it, or set allow_damaged_images: true in the "
            "params to score them as decoded (each is then listed in the run's manifest.json)"
        )
    return damaged


def check_writable_folder(params: dict[str, Any], key: str) -> Path:
    """Make ``params[key]`` (a folder) if needed and write a file in it."""
    check_folder_can_be_made(params, key)
    folder = Path(params[key])
    try:
        folder.mkdir(parents=True, exist_ok=True)
        with tempfile.NamedTemporaryFile(dir=folder, prefix=".write-check-"):
            pass
    except OSError as error:
        raise config.ParamsError(
            f"{config.blame(params, key)}: cannot write in {key} {folder} ({error.strerror or type(error).__name__}); "
            f"set {key} (or pass {config.option_name(key)}) to a folder you can write in"
        ) from None
    return folder


def check_folder_can_be_made(params: dict[str, Any], key: str) -> None:
    """``params[key]`` is a writable folder or could be made one; nothing is created."""
    folder = Path(params[key])
    flag = config.option_name(key)
    if folder.exists() and not folder.is_dir():
        raise config.ParamsError(
            f"{config.blame(params, key)}: {key} {folder} is a file, not a folder; set {key} (or pass {flag}) to a folder"
        )
    existing = next(p for p in (folder, *folder.parents) if p.exists())
    if not existing.is_dir() or not os.access(existing, os.W_OK | os.X_OK):
        what = "is a file" if not existing.is_dir() else "cannot be written"
        raise config.ParamsError(
            f"{config.blame(params, key)}: cannot write in {key} {folder} ({existing} {what}); "
            f"set {key} (or pass {flag}) to a folder you can write in"
        )


def device_problem(device: str) -> str | None:
    """Why ``device`` cannot be used here, or None; torch is imported only for a named GPU."""
    if device in ("auto", "cpu"):
        return None
    import torch

    if device == "mps":
        return None if torch.backends.mps.is_available() else "this machine's torch has no MPS (Apple GPU) device"
    if torch.version.cuda is None:
        return f"this torch ({torch.__version__}) is built without CUDA"
    count = torch.cuda.device_count() if torch.cuda.is_available() else 0
    if count == 0:
        return "no CUDA device is visible (check the driver and CUDA_VISIBLE_DEVICES)"
    index = int(device.partition(":")[2] or 0)
    if index >= count:
        return f"only {count} CUDA device(s) are visible (cuda:0 to cuda:{count - 1})"
    return None


def _check_frame_tolerance_options(params: dict[str, Any]) -> list[sequences.Pair]:
    """The pairs the frame_tolerance builder would make (nothing written), its options checked."""
    import inspect

    options = params["builder_options"]
    where = f"{config.blame(params, 'builder_options')}: builder_options"
    given = ("query_names", "reference_names", "seed")
    rule = [k for k in inspect.signature(frame_tolerance_pairs).parameters if k not in given]
    known = ["query_folder", "reference_folder", *rule]
    unknown = [k for k in options if k not in known]
    if unknown:
        raise config.ParamsError(
            f"{where}: unknown option(s) {unknown_keys_hint(unknown, known)}; known: {', '.join(known)}"
        )
    for key in ("query_folder", "reference_folder"):
        if not isinstance(options.get(key), str) or not options[key]:
            raise config.ParamsError(
                f"{where}: {key} must name a folder of images under image_root, got {options.get(key)!r}"
            )
    return sequence_build.frame_tolerance_sequence_pairs(params)


def check_labels_defined(sequence: Sequence, params: dict[str, Any]) -> None:
    """Refuse pairs (as ``limit`` cuts them) without a positive or a negative: AP and MR would be undefined."""
    limited = f" (its first {params['limit']} pairs, the limit)" if params["limit"] else ""
    where = f"{config.blame(params, 'pairs')}: the pair file {params['pairs']}{limited}"
    metrics.check_defined([pair.label for pair in sequence.pairs], where)


def check_run_inputs(
    params: dict[str, Any], images: bool = True, allow_other_weights: bool = False
) -> dict[str, str] | None:
    """Refuse, before any work, what a run cannot use: device, folders, weights (missing, or other than
    published unless ``allow_other_weights``), builder options and (``images``) the pair file and every
    image it names, each problem named as what it is. Returns the damaged images allowed
    (``check_image_contents``) when it checked every image, else None (a builder's pairs are checked once built)."""
    from gvbench_nb.protocol import weights

    problem = device_problem(params["device"])
    if problem:
        raise config.ParamsError(
            f"{config.blame(params, 'device')}: device {params['device']!r} cannot be used: {problem}; "
            "set device: auto (CUDA when available, else the CPU) or cpu"
        )
    check_folder_can_be_made(params, "output_dir")
    check_folder_can_be_made(params, "cache_dir")
    needed = [c for m in params["methods"] for c in method_registry.required_checkpoints(m, params["profile"])]
    missing = [c for c in needed if not weights.is_present(c)]
    if missing:
        raise weights.MissingWeightsError(
            "cannot run: weights missing (or drop the methods that need them, e.g. --methods all-available)\n"
            + "\n".join(weights.missing_message(c) for c in dict.fromkeys(missing))
        )
    other = "" if allow_other_weights else weights.other_weights_message(needed)
    if other:
        raise weights.OtherWeightsError(other)
    for method in params["methods"]:
        if method_registry.is_imm(method):
            method_registry.imm_peer().require(method)
        elif method_registry.resolve_method(method, params["profile"])["matcher"].get("metric") == "hamming":
            from gvbench_nb.protocol.matching.nearest_neighbour import hamming_kernel

            hamming_kernel()  # the compiled kernel of Hamming matching, refused if the checkout was not set up
    if not images:
        return None
    root = sequence_build.check_image_root(params)
    builder = params["pairs_builder"]
    options = params["builder_options"]
    if builder == sequence_build.BUILDER_NAME:
        try:
            parsed = build_inputs.parse_options(options, f"{config.blame(params, 'builder_options')}: builder_options")
        except build_inputs.BuildError as error:
            raise config.ParamsError(str(error)) from None
        for folder in (parsed.query_folder, *parsed.reference_folders):
            if not (root / folder).is_dir() and not options.get("render_sample"):
                raise config.ParamsError(
                    f"{config.blame(params, 'builder_options')}: builder_options names the image folder {folder!r}, "
                    f"but {root / folder} {path_problem(root / folder) or 'is not a folder'}; "
                    "set the folder names (or image_root) to folders of images"
                )
    if builder == "frame_tolerance":
        pairs = _check_frame_tolerance_options(params)
    elif builder is not None:
        return None  # the builder makes the pair file and images: ``run`` checks them once built
    else:
        if path_problem(params["pairs"]) is not None:
            raise sequence_build.missing_pairs_error(params)
        pairs = read_pairs(params["pairs"])
    origin = {"pairs_file": params["pairs"]}
    sequence = Sequence(params["sequence"], root, pairs, origin=origin).limited(params["limit"])
    check_labels_defined(sequence, params)  # what the pair file alone decides, before any image is read
    sequence.check_images()
    return check_image_contents(sequence, params["cache_dir"], params["allow_damaged_images"])
