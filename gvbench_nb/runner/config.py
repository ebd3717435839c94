"""Params files (one YAML a sequence, the notebooks' papermill parameters) and how a
sequence is prepared from them.

Relative paths in a params file are relative to the file's folder. ``${NAME}``
expands from the environment; ``${GVBENCH_DATA}`` is the data folder of ``data.data_dir``
(``$GVBENCH_DATA``, else a per-user cache folder that ``python -m gvbench_nb data fetch`` fills).
"""

from __future__ import annotations

import json
import os
import re
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import Annotated, Any

import yaml
from pydantic import BaseModel, ConfigDict, Field, InstanceOf, StringConstraints, ValidationError

from gvbench_nb import GVBenchError
from gvbench_nb import methods as method_registry
from gvbench_nb.data import build_inputs, fetch
from gvbench_nb.data.sequences import (
    Pair,
    Sequence,
    frame_tolerance_pairs,
    read_pairs,
    write_pairs,
)
from gvbench_nb.io_utils import atomic_write_json, atomic_write_text, file_sha256, unknown_keys_hint
from gvbench_nb.protocol import registry
from gvbench_nb.protocol.images import IMAGE_EXTENSIONS, path_problem
from gvbench_nb.runner import input_checks, sequence_build

PROJECT_ROOT = Path(__file__).resolve().parents[2]


class ParamsError(GVBenchError, ValueError):
    """A params file is malformed: missing, misspelled or invalid keys or values."""


PATH_KEYS = ("pairs", "image_root", "output_dir", "cache_dir")
PathValue = str | InstanceOf[os.PathLike]  # overrides from code may be Path objects
DEVICE_PATTERN = r"^(auto|cpu|mps|cuda(:\d+)?)$"


def _what(text: str, **kwargs: Any) -> Any:
    """A field whose ``description`` is what a refusal says its value must be."""
    return Field(description=text, **kwargs)


class ParamsModel(BaseModel):
    """A params file's keys: the required ones first, then the optional ones with their defaults."""

    model_config = ConfigDict(extra="forbid", strict=True)

    sequence: Annotated[str, StringConstraints(pattern=r"\S")] = _what("a non-empty name")
    pairs: PathValue = _what("a path")
    image_root: PathValue | None = _what("a folder path")
    methods: str | list[str] = _what("a list of method names or a comma-separated string")
    profile: str = _what("a profile name")
    output_dir: PathValue = _what("a folder path")
    description: str = _what("text", default="")
    pairs_builder: str | None = _what("a builder name or null", default=None)  # makes `pairs` when missing
    builder_options: dict[str, Any] = _what("a mapping of option names to values", default={})
    limit: Annotated[int, Field(gt=0)] | None = _what("a positive integer or null", default=None)  # first N pairs
    seed: int = _what("an integer", default=0, ge=0)  # RANSAC and every random choice; numpy refuses < 0
    device: Annotated[str, StringConstraints(pattern=DEVICE_PATTERN)] = _what(
        "'auto', 'cpu', 'cuda', 'cuda:N' or 'mps'", default="auto"
    )  # auto = cuda when available, else cpu
    cache_dir: PathValue | None = _what("a folder path or null", default=None)  # None: <output_dir>/../cache
    verifier: dict[str, Any] = _what("a mapping of verifier conf keys to values", default={})  # methods.VERIFIER
    allow_damaged_images: bool = _what("true or false", default=False)  # score images whose decoder warns


REQUIRED_KEYS = tuple(k for k, f in ParamsModel.model_fields.items() if f.is_required())
OPTIONAL_KEYS: dict[str, Any] = {
    k: f.get_default(call_default_factory=True) for k, f in ParamsModel.model_fields.items() if not f.is_required()
}


def _validate(params: dict[str, Any], path: Path) -> None:
    """Validate on ``ParamsModel``; its errors become the one sentence a user reads: unknown keys,
    else missing keys, else each wrong value with what it must be (an option's before the file's)."""
    try:
        ParamsModel.model_validate({k: v for k, v in params.items() if k not in ("params_file", "overridden")})
        return
    except ValidationError as error:
        errors = error.errors()
    valid = list(ParamsModel.model_fields)
    unknown = [str(e["loc"][0]) for e in errors if e["type"] == "extra_forbidden"]
    if unknown:
        raise ParamsError(f"{path}: unknown key(s) {unknown_keys_hint(unknown, valid)}. Valid keys: {', '.join(valid)}")
    if any(e["type"] == "missing" for e in errors):
        missing = [k for k in REQUIRED_KEYS if k not in params]
        raise ParamsError(f"{path}: missing key(s) {', '.join(missing)}. Required keys: {', '.join(REQUIRED_KEYS)}")
    wrong: dict[str, dict[str, str]] = {}
    for e in errors:
        key = str(e["loc"][0])
        what = ParamsModel.model_fields[key].description
        if e["type"] == "greater_than_equal":
            what = f"{what} of at least {e['ctx']['ge']}"
        wrong.setdefault(blame(params, key), {}).setdefault(key, f"{key} must be {what}, got {params[key]!r}")
    source = sorted(wrong, key=lambda where: not where.startswith("--"))[0]
    raise ParamsError(f"{source}: " + "; ".join(wrong[source].values()))


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


class _UniqueKeyLoader(yaml.SafeLoader):
    """YAML's safe loader, refusing a key given twice in one mapping (YAML itself keeps the last)."""


def _unique_mapping(loader: _UniqueKeyLoader, node: yaml.MappingNode, deep: bool = False) -> dict[Any, Any]:
    seen: dict[Any, int] = {}
    for key_node, _ in node.value:
        if key_node.tag == "tag:yaml.org,2002:merge":  # '<<: *anchor' merges, it is not a key
            continue
        key = loader.construct_object(key_node, deep=True)
        line = key_node.start_mark.line + 1
        try:
            first = seen.get(key)
            seen.setdefault(key, line)
        except TypeError:  # an unhashable key: the constructor below reports it
            continue
        if first is not None:  # block or flow style ({a: 1, a: 2} holds both on one line)
            source = getattr(loader, "source_name", key_node.start_mark.name)
            raise ParamsError(
                f"{source}:{line}: key {key!r} is given twice (first on "
                f"{'the same line' if first == line else f'line {first}'}); "
                "YAML would silently keep the last one, so keep only the one you mean"
            )
    return loader.construct_mapping(node, deep=deep)


_UniqueKeyLoader.add_constructor(yaml.resolver.BaseResolver.DEFAULT_MAPPING_TAG, _unique_mapping)


def read_yaml_mapping(path: Path) -> dict[str, Any]:
    """A params file's YAML mapping; a key given twice is refused with file:line."""
    with open(path, encoding="utf-8") as handle:
        loader = _UniqueKeyLoader(handle)
        loader.source_name = str(path)
        try:
            raw = loader.get_single_data() or {}
        except yaml.YAMLError as error:
            raise ParamsError(f"{path}: not valid YAML: {error}") from None
        finally:
            loader.dispose()
    if not isinstance(raw, dict):
        raise ParamsError(f"{path}: expected a mapping of keys to values, got {type(raw).__name__}")
    return raw


def option_name(key: str) -> str:
    """How the command line spells the override of a params key (``image_root`` -> ``--image-root``)."""
    return "--" + key.replace("_", "-")


def blame(params: dict[str, Any], key: str) -> str:
    """Where a params value came from, as an error names it: its option, else the params file."""
    return option_name(key) if key in params.get("overridden", ()) else str(params["params_file"])


def load_params(path: str | os.PathLike[str], **overrides: Any) -> dict[str, Any]:
    """Read, validate and resolve a params file; ``overrides`` (not None) replace keys.

    A wrong value is blamed on where it came from: an override on its option
    (``--methods``), any other value on the params file. ``params["overridden"]`` lists
    the overridden keys.
    """
    path = Path(path).resolve()
    if path.is_dir():
        examples = sorted(p.name for p in path.glob("*.yaml"))[:3]
        raise ParamsError(
            f"params path {path} is a folder, not a params file; give a YAML file"
            + (f" such as {path / examples[0]}" if examples else "")
        )
    if not path.is_file():
        problem = path_problem(path) or "is not a regular file"
        raise ParamsError(f"params file {path} {problem}; give the path of a params YAML (e.g. params/sample.yaml)")
    raw = read_yaml_mapping(path)
    given = {k: v for k, v in overrides.items() if v is not None}
    raw.update(given)
    params = {**OPTIONAL_KEYS, **raw, "params_file": str(path), "overridden": sorted(given)}
    _validate(params, path)
    try:
        params["methods"] = method_registry.expand_methods(params["methods"])
    except KeyError as error:
        raise ParamsError(f"{blame(params, 'methods')}: {error}") from None
    try:
        method_registry.check_profile(params["profile"])
    except KeyError as error:
        raise ParamsError(f"{blame(params, 'profile')}: {error}") from None
    if not params["methods"]:
        raise ParamsError(
            f"{blame(params, 'methods')}: methods is empty; name at least one (python -m gvbench_nb methods lists them)"
        )
    if params["pairs_builder"] is not None:
        try:
            registry.lookup("pairs_builder", params["pairs_builder"], PAIR_BUILDERS)
        except registry.UnknownNameError as error:
            raise ParamsError(f"{blame(params, 'pairs_builder')}: {error}") from None
    try:
        method_registry.check_verifier_overrides(params["verifier"])
    except (KeyError, ValueError) as error:
        raise ParamsError(f"{blame(params, 'verifier')}: verifier: {error}") from None
    for key in PATH_KEYS:
        value = params.get(key)
        if value is None:
            continue
        if "\0" in str(value):
            raise ParamsError(f"{blame(params, key)}: {key} holds a NUL byte, which no path can; fix the path")
        value = Path(_expand(str(value), str(path), key)).expanduser()
        params[key] = str(value if value.is_absolute() else (path.parent / value).resolve())
    if params["cache_dir"] is None:
        params["cache_dir"] = str(Path(params["output_dir"]).parent / "cache")
    input_checks.check_environment()
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
    if params["pairs_builder"] != sequence_build.BUILDER_NAME:
        raise build_inputs.BuildError(
            f"{params['params_file']}: pairs_builder is {params['pairs_builder']!r}; "
            f"building needs pairs_builder: {sequence_build.BUILDER_NAME} with its builder_options"
        )
    options = dict(params["builder_options"])
    options.update({k: v for k, v in (("descriptor", descriptor), ("top_n", top_n)) if v is not None})
    build_inputs.parse_options(options, f"{params['params_file']}: builder_options")  # fail before any work
    params["builder_options"] = options
    return params


# ------------------------------------------------------------------ builders --
def build_sample(params: dict[str, Any]) -> None:
    """The embedded default: a synthetic route rendered by the package (seconds, no download)."""
    from gvbench_nb.data import synthetic

    options = dict(params["builder_options"])
    synthetic.generate_sample(Path(params["image_root"]), seed=params["seed"], **options)


def frame_tolerance_sequence_pairs(params: dict[str, Any]) -> list[Pair]:
    """The pairs the frame_tolerance builder makes of the params' two image folders."""
    options = dict(params["builder_options"])
    root = Path(params["image_root"])
    query_folder = options.pop("query_folder")
    reference_folder = options.pop("reference_folder")

    def names(folder: str) -> list[str]:
        directory = root / folder
        if not directory.is_dir():
            raise ParamsError(
                f"{params['params_file']}: image folder {directory} not found (image_root {root}, folder {folder!r})"
                + (fetch.fetch_hint(directory) or "; set image_root to the folder holding it")
            )
        return sorted(f"{folder}/{p.name}" for p in directory.iterdir() if p.suffix.lower() in IMAGE_EXTENSIONS)

    try:
        return frame_tolerance_pairs(names(query_folder), names(reference_folder), seed=params["seed"], **options)
    except (TypeError, ValueError) as error:
        raise ParamsError(f"{params['params_file']}: builder_options: {error}") from None


def build_frame_tolerance(params: dict[str, Any]) -> None:
    """Rule-built pairs of a frame-aligned sequence (see ``sequences.frame_tolerance_pairs``)."""
    pairs = frame_tolerance_sequence_pairs(params)
    # Rebuilt on every run (milliseconds, seeded): a pair file made under other options is
    # replaced, and an unchanged one is left untouched.
    if not Path(params["pairs"]).is_file() or read_pairs(params["pairs"]) != pairs:
        write_pairs(params["pairs"], pairs)


def build_retrieval(params: dict[str, Any]) -> None:
    """GV-Bench's way: top-N retrieval by a global descriptor, labelled by a rule (``build.py``)."""
    sequence_build.build_retrieval_pairs(params)


PAIR_BUILDERS: dict[str, Callable[[dict[str, Any]], None]] = {
    "sample": build_sample,
    "frame_tolerance": build_frame_tolerance,
    "retrieval": build_retrieval,
}


def builder_stamp_path(pairs: str | os.PathLike[str]) -> Path:
    """``<pairs>.builder.json``: what built a pair file (builder, options, seed, image root)."""
    pairs = Path(pairs)
    return pairs.with_name(pairs.name + ".builder.json")


def builder_stamp(params: dict[str, Any]) -> dict[str, Any]:
    """What a builder's output depends on, as JSON would read it back: the builder, its
    options, the seed, the image root and (retrieval) what it read there
    (``build_inputs.inputs_digest``: the image folders' listings, the metadata and label files)."""
    stamp = {
        "pairs_builder": params["pairs_builder"],
        "builder_options": params["builder_options"],
        "seed": params["seed"],
        "image_root": params["image_root"],
    }
    if params["pairs_builder"] == sequence_build.BUILDER_NAME and params["image_root"] is not None:
        stamp["inputs"] = build_inputs.inputs_digest(params["image_root"], params["builder_options"])
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
    what = path_problem(pairs) or "is not a pair file"
    what = "is a folder, not a pair file" if what == "is a folder, not a file" else what
    return ParamsError(
        f"{params['params_file']}: the pair file {pairs} {what}; set pairs to a file of "
        "'query_path reference_path label' lines, or set pairs_builder to make it"
    )


def _check_image_root(params: dict[str, Any]) -> Path:
    """The image root, refused when unset, or (unless the sample builder renders it) not a folder."""
    source = blame(params, "image_root")
    if params["image_root"] is None:
        raise ParamsError(
            f"{source}: image_root is not set. Set it (or pass --image-root) to the folder holding the images "
            f"that the pair file's paths are relative to (e.g. the GV-Bench image root with day0/, night0/, ...)"
        )
    root = Path(params["image_root"])
    renders = params["pairs_builder"] == "sample" or (
        params["pairs_builder"] == sequence_build.BUILDER_NAME and params["builder_options"].get("render_sample")
    )
    if renders and "image_root" in params["overridden"] and not (root / "generator.json").is_file():
        # A folder typed on the command line names images; a builder renders only into the params file's.
        what = "holds no rendered route" if root.is_dir() else "does not exist"
        raise ParamsError(
            f"--image-root {root} {what}: a folder given on the command line must hold the images, it is never "
            f"rendered into; drop --image-root to render into the params file's image_root, or set image_root "
            f"in a params file of your own (its pairs_builder renders the route there)"
        )
    if params["pairs_builder"] != "sample" and not root.is_dir():  # the sample builder renders into the root
        what = "is a file, not a folder" if root.exists() else "does not exist"
        raise ParamsError(
            f"{source}: image_root {root} {what}"
            + (
                fetch.fetch_hint(root)
                or "; set image_root (or pass --image-root) to the folder "
                "holding the images that the pair file's paths are relative to"
            )
        )
    return root


def prepare_sequence(params: dict[str, Any]) -> Sequence:
    """The sequence of a params file, building its pairs (and images) when a builder is set.

    A builder's pair file is rebuilt whenever its builder, options, seed, image root or
    (retrieval) the images it read differ from those recorded beside it (``<pairs>.builder.json``) or the file changed
    since: a pair file made by a builder belongs to it, so change the options, not the file.
    """
    root = _check_image_root(params)
    builder = params["pairs_builder"]
    if builder and (builder == "sample" or not _stamp_matches(params)):
        builder_stamp_path(params["pairs"]).unlink(missing_ok=True)  # a killed build then rebuilds
        PAIR_BUILDERS[builder](params)
        atomic_write_json(
            builder_stamp_path(params["pairs"]), {**builder_stamp(params), "pairs_sha256": file_sha256(params["pairs"])}
        )
    if path_problem(params["pairs"]) is not None:
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


def check_folder_can_be_made(params: dict[str, Any], key: str) -> None:
    """``params[key]`` is a folder that can be written, or one that could be made: checked
    without creating anything (``check_writable_folder`` makes it once every check passed)."""
    folder = Path(params[key])
    flag = option_name(key)
    if folder.exists() and not folder.is_dir():
        raise ParamsError(
            f"{blame(params, key)}: {key} {folder} is a file, not a folder; set {key} (or pass {flag}) to a folder"
        )
    existing = next(p for p in (folder, *folder.parents) if p.exists())
    if not existing.is_dir() or not os.access(existing, os.W_OK | os.X_OK):
        what = "is a file" if not existing.is_dir() else "cannot be written"
        raise ParamsError(
            f"{blame(params, key)}: cannot write in {key} {folder} ({existing} {what}); "
            f"set {key} (or pass {flag}) to a folder you can write in"
        )


def device_problem(device: str) -> str | None:
    """Why ``device`` (a params ``device`` value) cannot be used here, or None.

    ``auto`` and ``cpu`` always can; torch is imported only to check a device named
    otherwise (a run on it imports torch anyway).
    """
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


def _check_frame_tolerance_options(params: dict[str, Any]) -> Sequence:
    """The frame_tolerance builder's options name two image folders and only the rule's
    parameters; returns the sequence it would build (nothing is written)."""
    import inspect

    options = params["builder_options"]
    where = f"{blame(params, 'builder_options')}: builder_options"
    rule = [
        k
        for k in inspect.signature(frame_tolerance_pairs).parameters
        if k not in ("query_names", "reference_names", "seed")
    ]
    known = ["query_folder", "reference_folder", *rule]
    unknown = [k for k in options if k not in known]
    if unknown:
        raise ParamsError(f"{where}: unknown option(s) {unknown_keys_hint(unknown, known)}; known: {', '.join(known)}")
    for key in ("query_folder", "reference_folder"):
        if not isinstance(options.get(key), str) or not options[key]:
            raise ParamsError(f"{where}: {key} must name a folder of images under image_root, got {options.get(key)!r}")
    pairs = frame_tolerance_sequence_pairs(params)
    return Sequence(params["sequence"], Path(params["image_root"]), pairs, origin={"pairs_file": params["pairs"]})


def check_run_inputs(params: dict[str, Any], images: bool = True) -> None:
    """Everything a run needs that can be checked before it writes a file or imports a
    model: the device, the output and cache folders, the weights, the builder's options and
    folders, and (``images``) the pair file and every image it names (each missing, broken
    link, link loop, folder or FIFO named as what it is). Raises the error a user reads."""
    from gvbench_nb.protocol import weights

    problem = device_problem(params["device"])
    if problem:
        raise ParamsError(
            f"{blame(params, 'device')}: device {params['device']!r} cannot be used: {problem}; "
            "set device: auto (CUDA when available, else the CPU) or cpu"
        )
    check_folder_can_be_made(params, "output_dir")
    check_folder_can_be_made(params, "cache_dir")
    input_checks.check_same_recipes(params)
    missing = [
        c
        for m in params["methods"]
        for c in method_registry.required_checkpoints(m, params["profile"])
        if not weights.is_present(c)
    ]
    if missing:
        raise weights.MissingWeightsError(
            "cannot run: weights missing (or drop the methods that need them, e.g. --methods all-available)\n"
            + "\n".join(weights.missing_message(c) for c in dict.fromkeys(missing))
        )
    for method in params["methods"]:
        if method_registry.is_imm(method):
            method_registry.imm_peer().require(method)
    if not images:
        return
    root = _check_image_root(params)
    builder = params["pairs_builder"]
    options = params["builder_options"]
    if builder == sequence_build.BUILDER_NAME:
        try:
            parsed = build_inputs.parse_options(options, f"{blame(params, 'builder_options')}: builder_options")
        except build_inputs.BuildError as error:
            raise ParamsError(str(error)) from None
        for folder in (parsed.query_folder, *parsed.reference_folders):
            if not (root / folder).is_dir() and not options.get("render_sample"):
                raise ParamsError(
                    f"{blame(params, 'builder_options')}: builder_options names the image folder {folder!r}, "
                    f"but {root / folder} {path_problem(root / folder) or 'is not a folder'}; "
                    "set the folder names (or image_root) to folders of images"
                )
    if builder == "frame_tolerance":
        sequence = _check_frame_tolerance_options(params).limited(params["limit"])
    elif builder is not None:
        return  # the builder makes the pair file and images: ``run`` checks them once built
    else:
        if path_problem(params["pairs"]) is not None:
            raise _missing_pairs_error(params)
        origin = {"pairs_file": params["pairs"]}
        sequence = Sequence(params["sequence"], root, read_pairs(params["pairs"]), origin=origin).limited(
            params["limit"]
        )
    sequence.check_images()
    input_checks.check_image_contents(sequence, params["cache_dir"], params["allow_damaged_images"])


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
