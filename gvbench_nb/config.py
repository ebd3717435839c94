"""Params files (one YAML a sequence, the notebooks' papermill parameters) and how a
sequence is prepared from them.

Relative paths in a params file are relative to the file's folder. ``${NAME}``
expands from the environment; ``${GVBENCH_DATA}`` is the data folder of ``data.data_dir``
(``$GVBENCH_DATA``, else a per-user cache folder that ``python -m gvbench_nb data fetch`` fills).
"""

from __future__ import annotations

import hashlib
import json
import os
import re
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

import yaml

from gvbench_nb import methods as method_registry
from gvbench_nb import registry
from gvbench_nb.data import builders, fetch
from gvbench_nb.data.sequences import (
    Sequence,
    frame_tolerance_pairs,
    read_pairs,
    write_pairs,
)
from gvbench_nb.io_utils import atomic_write_json, atomic_write_text

PROJECT_ROOT = Path(__file__).resolve().parent.parent

REQUIRED_KEYS = ("sequence", "pairs", "image_root", "methods", "profile", "output_dir")
OPTIONAL_KEYS: dict[str, Any] = {
    "description": "",
    "pairs_builder": None,  # name in PAIR_BUILDERS: makes `pairs` (and images) when missing
    "builder_options": {},
    "limit": None,  # first N pairs only
    "seed": 0,  # RANSAC and every random choice
    "device": "auto",  # auto = cuda when available, else cpu
    "cache_dir": None,  # default: <output_dir>/../cache (shared by sequences)
    "verifier": {},  # overrides of the profile's verifier conf, e.g. {method: USAC_MAGSAC} (methods.VERIFIER)
}
PATH_KEYS = ("pairs", "image_root", "output_dir", "cache_dir")


class ParamsError(ValueError):
    """A params file is malformed: missing, misspelled or invalid keys or values."""


def data_dir() -> Path:
    """The data folder: $GVBENCH_DATA, else the per-user cache folder (see ``data.data_dir``)."""
    return fetch.data_dir()


def _expand(value: str, source: str, key: str) -> str:
    def replace(match: re.Match[str]) -> str:
        name = match.group(1)
        if name == "GVBENCH_DATA":
            return str(data_dir())
        if name not in os.environ:
            raise ParamsError(f"{source}: {key} uses ${{{name}}}, which is not set in the environment")
        return os.environ[name]

    return re.sub(r"\$\{([A-Za-z_][A-Za-z0-9_]*)\}", replace, value)


def load_params(path: str | os.PathLike[str], **overrides: Any) -> dict[str, Any]:
    """Read, validate and resolve a params file; ``overrides`` (not None) replace keys."""
    path = Path(path).resolve()
    if path.is_dir():
        examples = sorted(p.name for p in path.glob("*.yaml"))[:3]
        raise ParamsError(
            f"params path {path} is a folder, not a params file; give a YAML file"
            + (f" such as {path / examples[0]}" if examples else "")
        )
    if not path.is_file():
        raise ParamsError(f"params file not found: {path}; give the path of a params YAML (e.g. params/sample.yaml)")
    with open(path, encoding="utf-8") as handle:
        try:
            raw = yaml.safe_load(handle) or {}
        except yaml.YAMLError as error:
            raise ParamsError(f"{path}: not valid YAML: {error}") from None
    if not isinstance(raw, dict):
        raise ParamsError(f"{path}: expected a mapping of keys to values, got {type(raw).__name__}")
    raw.update({k: v for k, v in overrides.items() if v is not None})
    valid = list(REQUIRED_KEYS) + list(OPTIONAL_KEYS)
    unknown = [k for k in raw if k not in valid]
    if unknown:
        raise ParamsError(
            f"{path}: unknown key(s) {registry.unknown_keys_hint(unknown, valid)}. Valid keys: {', '.join(valid)}"
        )
    missing = [k for k in REQUIRED_KEYS if k not in raw]
    if missing:
        raise ParamsError(f"{path}: missing key(s) {', '.join(missing)}. Required keys: {', '.join(REQUIRED_KEYS)}")
    params = {**OPTIONAL_KEYS, **raw}
    params["params_file"] = str(path)
    _check_types(params, path)
    try:
        params["methods"] = method_registry.expand_methods(params["methods"])
        method_registry.check_profile(params["profile"])
    except KeyError as error:
        raise ParamsError(f"{path}: {error}") from None
    if not params["methods"]:
        raise ParamsError(f"{path}: methods is empty; name at least one (python -m gvbench_nb methods lists them)")
    if params["pairs_builder"] is not None:
        try:
            registry.lookup("pairs_builder", params["pairs_builder"], PAIR_BUILDERS)
        except registry.UnknownNameError as error:
            raise ParamsError(f"{path}: {error}") from None
    try:
        method_registry.check_verifier_overrides(params["verifier"])
    except (KeyError, ValueError) as error:
        raise ParamsError(f"{path}: verifier: {error}") from None
    if params["limit"] is not None and params["limit"] < 1:
        raise ParamsError(f"{path}: limit must be a positive integer or null, got {params['limit']!r}")
    for key in PATH_KEYS:
        value = params.get(key)
        if value is None:
            continue
        value = Path(_expand(str(value), str(path), key)).expanduser()
        params[key] = str(value if value.is_absolute() else (path.parent / value).resolve())
    if params["cache_dir"] is None:
        params["cache_dir"] = str(Path(params["output_dir"]).parent / "cache")
    return params


def load_build_params(
    params_file: str | Path,
    descriptor: str | None = None,
    top_n: int | None = None,
    pairs: str | None = None,
    **overrides: Any,
) -> dict[str, Any]:
    """``load_params`` of a ``pairs_builder: retrieval`` file, with build overrides."""
    params = load_params(params_file, pairs=pairs, **overrides)
    if params["pairs_builder"] != builders.BUILDER_NAME:
        raise builders.BuildError(
            f"{params['params_file']}: pairs_builder is {params['pairs_builder']!r}; "
            f"building needs pairs_builder: {builders.BUILDER_NAME} with its builder_options"
        )
    options = dict(params["builder_options"])
    options.update({k: v for k, v in (("descriptor", descriptor), ("top_n", top_n)) if v is not None})
    builders.parse_options(options, f"{params['params_file']}: builder_options")  # fail before any work
    params["builder_options"] = options
    return params


def _is_integer(value: Any) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)  # YAML 'yes' is a bool, not 1


def _is_path(value: Any) -> bool:
    return isinstance(value, (str, os.PathLike))  # overrides from code may be Path objects


DEVICE_PATTERN = re.compile(r"auto|cpu|mps|cuda(:\d+)?")

# key -> (check, what the value must be); None passes where the key allows it.
TYPE_CHECKS: dict[str, tuple[Callable[[Any], bool], str]] = {
    "sequence": (lambda v: isinstance(v, str) and bool(v.strip()), "a non-empty name"),
    "pairs": (lambda v: _is_path(v), "a path"),
    "image_root": (lambda v: v is None or _is_path(v), "a folder path"),
    "output_dir": (lambda v: _is_path(v), "a folder path"),
    "cache_dir": (lambda v: v is None or _is_path(v), "a folder path or null"),
    "methods": (
        lambda v: isinstance(v, str) or (isinstance(v, list) and all(isinstance(m, str) for m in v)),
        "a list of method names or a comma-separated string",
    ),
    "profile": (lambda v: isinstance(v, str), "a profile name"),
    "description": (lambda v: isinstance(v, str), "text"),
    "pairs_builder": (lambda v: v is None or isinstance(v, str), "a builder name or null"),
    "builder_options": (lambda v: isinstance(v, dict), "a mapping of option names to values"),
    "limit": (lambda v: v is None or _is_integer(v), "a positive integer or null"),
    "seed": (_is_integer, "an integer"),
    "verifier": (lambda v: isinstance(v, dict), "a mapping of verifier conf keys to values"),
    "device": (
        lambda v: isinstance(v, str) and DEVICE_PATTERN.fullmatch(v) is not None,
        "'auto', 'cpu', 'cuda', 'cuda:N' or 'mps'",
    ),
}


def _check_types(params: dict[str, Any], source: Path) -> None:
    """Every key's value has the right kind; the error names the key and what it must be."""
    wrong = [
        f"{key} must be {what}, got {params[key]!r}"
        for key, (check, what) in TYPE_CHECKS.items()
        if key in params and not check(params[key])
    ]
    if wrong:
        raise ParamsError(f"{source}: " + "; ".join(wrong))


# ------------------------------------------------------------------ builders --
def build_sample(params: dict[str, Any]) -> None:
    """The embedded default: a synthetic route rendered by the package (seconds, no download)."""
    from gvbench_nb.data import synthetic

    options = dict(params["builder_options"])
    synthetic.generate_sample(Path(params["image_root"]), seed=params["seed"], **options)


def build_frame_tolerance(params: dict[str, Any]) -> None:
    """Rule-built pairs of a frame-aligned sequence (see ``sequences.frame_tolerance_pairs``)."""
    options = dict(params["builder_options"])
    root = Path(params["image_root"])
    query_folder = options.pop("query_folder")
    reference_folder = options.pop("reference_folder")
    extensions = {".jpg", ".jpeg", ".png", ".ppm", ".bmp"}

    def names(folder: str) -> list[str]:
        directory = root / folder
        if not directory.is_dir():
            raise ParamsError(
                f"{params['params_file']}: image folder {directory} not found (image_root {root}, folder {folder!r})"
                + (fetch.fetch_hint(directory) or "; set image_root to the folder holding it")
            )
        return sorted(f"{folder}/{p.name}" for p in directory.iterdir() if p.suffix.lower() in extensions)

    try:
        pairs = frame_tolerance_pairs(names(query_folder), names(reference_folder), seed=params["seed"], **options)
    except (TypeError, ValueError) as error:
        raise ParamsError(f"{params['params_file']}: builder_options: {error}") from None
    # Rebuilt on every run (milliseconds, seeded): a pair file made under other options is
    # replaced, and an unchanged one is left untouched.
    if not Path(params["pairs"]).is_file() or read_pairs(params["pairs"]) != pairs:
        write_pairs(params["pairs"], pairs)


def build_retrieval(params: dict[str, Any]) -> None:
    """GV-Bench's way: top-N retrieval by a global descriptor, labelled by a rule (``build.py``)."""
    builders.build_retrieval_pairs(params)


PAIR_BUILDERS: dict[str, Callable[[dict[str, Any]], None]] = {
    "sample": build_sample,
    "frame_tolerance": build_frame_tolerance,
    "retrieval": build_retrieval,
}


def file_sha256(path: str | os.PathLike[str]) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as stream:
        for block in iter(lambda: stream.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def builder_stamp_path(pairs: str | os.PathLike[str]) -> Path:
    """``<pairs>.builder.json``: what built a pair file (builder, options, seed, image root)."""
    pairs = Path(pairs)
    return pairs.with_name(pairs.name + ".builder.json")


def builder_stamp(params: dict[str, Any]) -> dict[str, Any]:
    """What a builder's output depends on, as JSON would read it back."""
    stamp = {
        "pairs_builder": params["pairs_builder"],
        "builder_options": params["builder_options"],
        "seed": params["seed"],
        "image_root": params["image_root"],
    }
    return json.loads(json.dumps(stamp, sort_keys=True, default=str))


def _stamp_matches(params: dict[str, Any]) -> bool:
    """The pair file was built by this builder, with these options and seed, and not changed since."""
    pairs, stamp_path = Path(params["pairs"]), builder_stamp_path(params["pairs"])
    if not pairs.is_file() or not stamp_path.is_file():
        return False
    try:
        recorded = json.loads(stamp_path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return False
    if not isinstance(recorded, dict):
        return False
    sha256 = recorded.pop("pairs_sha256", None)
    return recorded == builder_stamp(params) and sha256 == file_sha256(pairs)


def _missing_pairs_error(params: dict[str, Any]) -> ParamsError:
    pairs = Path(params["pairs"])
    what = "is a folder, not a pair file" if pairs.is_dir() else "does not exist"
    return ParamsError(
        f"{params['params_file']}: the pair file {pairs} {what}; set pairs to a file of "
        "'query_path reference_path label' lines, or set pairs_builder to make it"
    )


def prepare_sequence(params: dict[str, Any]) -> Sequence:
    """The sequence of a params file, building its pairs (and images) when a builder is set.

    A builder's pair file is rebuilt whenever its builder, options, seed or image root
    differ from those recorded beside it (``<pairs>.builder.json``) or the file changed
    since: a pair file made by a builder belongs to it, so change the options, not the file.
    """
    source = params["params_file"]
    if params["image_root"] is None:
        raise ParamsError(
            f"{source}: image_root is not set. Set it (or pass --image-root) to the folder holding the images "
            f"that the pair file's paths are relative to (e.g. the GV-Bench image root with day0/, night0/, ...)"
        )
    root = Path(params["image_root"])
    builder = params["pairs_builder"]
    if builder != "sample" and not root.is_dir():  # the sample builder renders its images into the root
        what = "is a file, not a folder" if root.exists() else "does not exist"
        raise ParamsError(
            f"{source}: image_root {root} {what}"
            + (
                fetch.fetch_hint(root)
                or "; set image_root (or pass --image-root) to the folder "
                "holding the images that the pair file's paths are relative to"
            )
        )
    if builder and (builder == "sample" or not _stamp_matches(params)):
        builder_stamp_path(params["pairs"]).unlink(missing_ok=True)  # a killed build then rebuilds
        PAIR_BUILDERS[builder](params)
        atomic_write_json(
            builder_stamp_path(params["pairs"]), {**builder_stamp(params), "pairs_sha256": file_sha256(params["pairs"])}
        )
    if not Path(params["pairs"]).is_file():
        raise _missing_pairs_error(params)
    sequence = Sequence(params["sequence"], root, read_pairs(params["pairs"]), origin=sequence_origin(params))
    return sequence.limited(params["limit"])


def sequence_origin(params: dict[str, Any]) -> dict[str, Any]:
    """Where a sequence's pairs came from, as run.json records it."""
    return {
        "params_file": params["params_file"],
        "pairs_file": params["pairs"],
        "pairs_sha256": file_sha256(params["pairs"]),
        "image_root": params["image_root"],
        "pairs_builder": params["pairs_builder"],
        "builder_options": params["builder_options"],
        "seed": params["seed"],
        "limit": params["limit"],
    }


def load_sequence_pairs_only(params: dict[str, Any]) -> Sequence:
    """Pairs without touching images (works for the official lists without their images)."""
    root = Path(params["image_root"]) if params["image_root"] else Path(".")
    if not Path(params["pairs"]).is_file():
        raise _missing_pairs_error(params)
    return Sequence(params["sequence"], root, read_pairs(params["pairs"])).limited(params["limit"])


def check_writable_folder(params: dict[str, Any], key: str) -> Path:
    """Create ``params[key]`` (a folder) if needed and check a file can be written in it."""
    folder = Path(params[key])
    flag = f"--{key.replace('_', '-')}"
    if folder.exists() and not folder.is_dir():
        raise ParamsError(
            f"{params['params_file']}: {key} {folder} is a file, not a folder; set {key} (or pass {flag}) to a folder"
        )
    try:
        folder.mkdir(parents=True, exist_ok=True)
        with tempfile.NamedTemporaryFile(dir=folder, prefix=".write-check-"):
            pass
    except OSError as error:
        raise ParamsError(
            f"{params['params_file']}: cannot write in {key} {folder} "
            f"({error.strerror or type(error).__name__}); set {key} (or pass {flag}) to a folder "
            "you can write in"
        ) from None
    return folder


RESOLVED_PARAMS_NAME = "params.resolved.yaml"


def write_resolved_params(params: dict[str, Any], folder: str | os.PathLike[str]) -> Path:
    """The params a run uses, command-line overrides applied and paths absolute, as one
    YAML the notebooks load (``<output_dir>/params.resolved.yaml``)."""
    keys = list(REQUIRED_KEYS) + list(OPTIONAL_KEYS)
    values = {key: params[key] for key in keys if key in params}
    header = (
        f"# The params this run used: {params['params_file']} with the command line's overrides.\n"
        "# Written by `python -m gvbench_nb run`; every notebook of the run loads this file.\n"
    )
    text = header + yaml.safe_dump(values, sort_keys=False, allow_unicode=True)
    return atomic_write_text(Path(folder) / RESOLVED_PARAMS_NAME, text)
