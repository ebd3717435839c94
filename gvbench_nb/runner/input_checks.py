"""Inputs checked by what they are before a run works: the environment's settings, the images'
contents (two images of one content are one image; a damaged image is named), and the recipe of
the methods an output folder keeps beside this run's.
"""

from __future__ import annotations

import json
import os
import sys
import tempfile
import threading
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from gvbench_nb import GVBenchError
from gvbench_nb import methods as method_registry
from gvbench_nb.data.sequences import PairFileError, Sequence, pair_line_numbers, read_pairs
from gvbench_nb.io_utils import atomic_write_json
from gvbench_nb.protocol.images import ImageReadError, max_pixels
from gvbench_nb.runner import concurrency, image_features, method_outputs, record


class SettingError(GVBenchError, ValueError):
    """An environment variable the package reads holds a value it cannot use."""


def check_environment() -> None:
    """Every environment variable the package reads holds a value it can use; the error names it."""
    try:
        concurrency.threads_of_environment()
        concurrency.job_count()
        max_pixels()
    except (ValueError, ImageReadError) as error:
        raise SettingError(str(error)) from None
    value = os.environ.get("GVBENCH_DATA") or ""
    if "\0" in value or (value and Path(value).expanduser().is_file()):
        raise SettingError(
            f"the environment variable GVBENCH_DATA (the data folder) must name a folder, got {value!r}; "
            "fix or unset it"
        )


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
    """What the decoder says of an image, "" when nothing: libjpeg's and libpng's warnings
    ("Corrupt JPEG data: premature end of data segment") go to the process's stderr, not to
    Python, so they are caught there while an eighth-size grey decode (every byte is still
    entropy-decoded; about a millisecond a frame) reads the file. A failed decode raises ``ImageReadError``."""
    data = np.fromfile(path, dtype=np.uint8)
    with _decoder_lock, tempfile.TemporaryFile() as said:
        sys.stderr.flush()
        saved = os.dup(2)
        os.dup2(said.fileno(), 2)
        try:
            image = cv2.imdecode(data, cv2.IMREAD_REDUCED_GRAYSCALE_8) if data.size else None
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


def content_keys(sequence: Sequence) -> dict[str, str]:
    """Image name -> content key (``image_features.content_key``: hashed once a process)."""
    keys = {}
    for name in sequence.images:
        try:
            keys[name] = image_features.image_key(sequence.image_root, name)
        except ImageReadError as error:
            raise ImageReadError(f"{error} ({image_features.first_pair_using(sequence, name)})") from None
    return keys


DECODER_CHECKS = "decoder-checks.json"  # in the cache folder: content key -> what its decoder said ("" nothing)


def decoder_messages(sequence: Sequence, keys: dict[str, str], cache_dir: Path) -> dict[str, str]:
    """Image name -> what its decoder said, for each image whose decoder said anything. Each content
    is decoded once: the answers are kept in ``<cache_dir>/decoder-checks.json`` (written only into
    a cache folder that exists: a check writes no folder)."""
    path = Path(cache_dir) / DECODER_CHECKS
    try:
        known = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        known = {}
    known = known if isinstance(known, dict) else {}
    unknown = {key: name for name, key in keys.items() if not isinstance(known.get(key), str)}
    for key, name in unknown.items():
        try:
            known[key] = decoder_message(Path(sequence.image_root) / name)
        except ImageReadError as error:
            raise ImageReadError(f"{error} ({image_features.first_pair_using(sequence, name)})") from None
    if unknown and path.parent.is_dir():
        atomic_write_json(path, known)  # two runs at once: the later file wins, the other's images are decoded again
    return {name: known[key] for name, key in keys.items() if known[key]}


def check_image_contents(sequence: Sequence, cache_dir: str | os.PathLike[str], allow_damaged: bool) -> dict[str, str]:
    """Refuse a pair of two images with one content (a copy or a link: a self-pair, as one named
    twice is) with file:line, and an image whose decoder fails, or warns unless ``allow_damaged``.
    Returns the damaged images allowed (name -> what the decoder said), for the run's record."""
    keys = content_keys(sequence)
    for index, pair in enumerate(sequence.pairs):
        query, reference = keys[pair.query], keys[pair.reference]
        if query == reference:
            raise PairFileError(
                f"{_where(sequence, index)}: self-pair by content: {pair.query} and {pair.reference} hold the same "
                "bytes (a copy of one image, or a link to it); a pair needs two different images, remove this line"
            )
    damaged = decoder_messages(sequence, keys, Path(cache_dir))
    if damaged and not allow_damaged:
        name, said = next(iter(damaged.items()))
        raise ImageReadError(
            f"{len(damaged)} of {len(keys)} images of sequence {sequence.name!r} are damaged, first "
            f"{Path(sequence.image_root) / name} ({image_features.first_pair_using(sequence, name)}): its decoder "
            f"said {said!r}; replace it, remove the pairs that use it, or set allow_damaged_images: true in the "
            "params to score them as decoded (each is then listed in the output folder's gvbench-run.json)"
        )
    return damaged


def _recipe_differences(run: dict[str, Any], params: dict[str, Any]) -> list[str]:
    """How a kept method's recorded verifier and seed differ from what this run would give it."""
    conf = run["conf"]
    wanted = method_registry.resolve_method(conf["method"], conf["profile"], params["verifier"])["verifier"]
    wanted, found = json.loads(json.dumps(wanted)), conf.get("verifier") or {}
    differences = [
        f"verifier {key} {found.get(key)!r} there, {wanted.get(key)!r} here"
        for key in sorted(set(found) | set(wanted))
        if found.get(key) != wanted.get(key)
    ]
    if run.get("seed") != params["seed"]:
        differences.append(f"seed {run.get('seed')!r} there, {params['seed']!r} here")
    return differences


def check_same_recipes(params: dict[str, Any]) -> None:
    """Refuse a run into a folder that keeps methods run under another verifier or seed than this
    run would give them: one table's rows share their recipe's verifier and seed."""
    output_dir = Path(params["output_dir"])
    differing = {}
    for method in (record.read_record(output_dir) or {}).get("methods", {}):
        if method in params["methods"]:
            continue
        try:
            run = json.loads((method_outputs.method_dir(output_dir, method) / "run.json").read_text(encoding="utf-8"))
            differences = _recipe_differences(run, params)
        except (OSError, ValueError, KeyError, TypeError):
            continue  # no run record to compare: the results readers refuse such a folder
        if differences:
            differing[method] = ", ".join(differences)
    if differing:
        described = "; ".join(f"{method}: {what}" for method, what in differing.items())
        raise record.RecordError(
            f"{output_dir} holds results made under another recipe than this run's ({described}), and one table "
            f"does not mix recipes; run them again with this run (--methods "
            f"{','.join([*params['methods'], *differing])}) or give another --output-dir"
        )
