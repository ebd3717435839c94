"""Params files: one YAML a sequence, the notebooks' papermill parameters.

Relative paths in a params file are relative to the file's folder. ``${NAME}``
expands from the environment; ``${GVBENCH_DATA}`` is the data folder of ``data.data_dir``
(``$GVBENCH_DATA``, else a per-user cache folder that ``python -m gvbench_nb data fetch`` fills).
A path under the repository's outputs/ is under ``$GVBENCH_OUTPUTS`` when that is set.
"""

from __future__ import annotations

import hashlib
import os
import re
from pathlib import Path
from typing import Annotated, Any

import yaml
from pydantic import AfterValidator, BaseModel, ConfigDict, Field, InstanceOf, StringConstraints, ValidationError
from pydantic_core import ErrorDetails

from gvbench_nb import GVBenchError
from gvbench_nb import methods as method_registry
from gvbench_nb.data import fetch
from gvbench_nb.data.sequences import name_problem, shorten
from gvbench_nb.io_utils import atomic_write_text, unknown_keys_hint
from gvbench_nb.protocol import registry
from gvbench_nb.protocol.images import ImageReadError, max_pixels, path_problem
from gvbench_nb.runner import concurrency

PROJECT_ROOT = Path(__file__).resolve().parents[2]
OUTPUTS_DIR = PROJECT_ROOT / "outputs"


class ParamsError(GVBenchError, ValueError):
    """A params file is malformed: missing, misspelled or invalid keys or values."""


PATH_KEYS = ("pairs", "image_root", "output_dir", "cache_dir")
PathValue = str | InstanceOf[os.PathLike]  # overrides from code may be Path objects
DEVICE_PATTERN = r"^(auto|cpu|mps|cuda(:\d+)?)$"
PAIR_BUILDER_NAMES = ("sample", "frame_tolerance", "retrieval")  # sequence_build.PAIR_BUILDERS makes each


def real_path(path: str | os.PathLike[str]) -> Path:
    """``path`` absolute with its links followed (``Path.resolve()``); a link loop stays as given, made
    absolute, for ``path_problem`` to name (``resolve`` raises ``RuntimeError`` there)."""
    try:
        return Path(path).resolve()
    except (RuntimeError, OSError):
        return Path(os.path.abspath(path))


def _what(text: str, **kwargs: Any) -> Any:
    """A field whose ``description`` is what a refusal says its value must be."""
    return Field(description=text, **kwargs)


def outputs_path(path: str | os.PathLike[str]) -> Path:
    """``path``, or where ``$GVBENCH_OUTPUTS`` puts it when it lies under the repository's outputs/:
    the shipped params files and the notebooks' defaults write there (the tests point it elsewhere)."""
    moved, path = os.environ.get("GVBENCH_OUTPUTS"), Path(path)
    if not moved or not real_path(path).is_relative_to(OUTPUTS_DIR):
        return path
    return Path(moved).expanduser().resolve() / real_path(path).relative_to(OUTPUTS_DIR)


def plain_name(name: str) -> str:
    """``name`` when ``name_problem`` finds none, else a ``ValueError`` saying what it is."""
    problem = name_problem(name)
    if problem:
        raise ValueError(problem)
    return name


class ParamsModel(BaseModel):
    """A params file's keys: the required ones first, then the optional ones with their defaults."""

    model_config = ConfigDict(extra="forbid", strict=True)

    sequence: Annotated[str, AfterValidator(plain_name)] = _what(
        "a plain name such as gardens_point_night (it names the output's files)"
    )
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
    cache_dir: PathValue | None = _what("a folder path or null", default=None)  # None: fetch.cache_dir()
    verifier: dict[str, Any] = _what("a mapping of verifier conf keys to values", default={})  # methods.VERIFIER
    allow_damaged_images: bool = _what("true or false", default=False)  # score images whose decoder warns


REQUIRED_KEYS = tuple(k for k, f in ParamsModel.model_fields.items() if f.is_required())
OPTIONAL_KEYS: dict[str, Any] = {
    k: f.get_default(call_default_factory=True) for k, f in ParamsModel.model_fields.items() if not f.is_required()
}


def _validate(params: dict[str, Any], path: str) -> None:
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
        wrong.setdefault(blame(params, key), {}).setdefault(key, _wrong_value(e, params[key]))
    source = sorted(wrong, key=lambda where: not where.startswith("--"))[0]
    raise ParamsError(f"{source}: " + "; ".join(wrong[source].values()))


def _wrong_value(error: ErrorDetails, value: Any) -> str:
    """A refused value in words: what its key must be, or what the field's own check (``plain_name``) found."""
    key = str(error["loc"][0])
    what = ParamsModel.model_fields[key].description
    if error["type"] == "value_error":
        return f"{key} {shorten(repr(value))} {error['ctx']['error']}; give {what}"
    if error["type"] == "greater_than_equal":
        what = f"{what} of at least {error['ctx']['ge']}"
    return f"{key} must be {what}, got {value!r}"


def check_value(key: str, value: Any, source: str) -> None:
    """One params key's value refused alone, in ``load_params``' words (a notebook's ``sequence`` is
    checked before it picks the params file of that sequence)."""
    try:
        ParamsModel.__pydantic_validator__.validate_assignment(ParamsModel.model_construct(), key, value)
    except ValidationError as error:
        raise ParamsError(f"{source}: {_wrong_value(error.errors()[0], value)}") from None


def _expand(value: str, source: str, key: str) -> str:
    def replace(match: re.Match[str]) -> str:
        name = match.group(1)
        if name == "GVBENCH_DATA":
            return str(fetch.data_dir())
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
    """Read, validate and resolve a params file; ``overrides`` (not None) replace keys and are
    listed in ``params["overridden"]``, so a wrong one is blamed on its option."""
    path = real_path(path)
    if path.is_dir():
        examples = sorted(p.name for p in path.glob("*.yaml"))[:3]
        raise ParamsError(
            f"params path {path} is a folder, not a params file; give a YAML file"
            + (f" such as {path / examples[0]}" if examples else "")
        )
    if not path.is_file():
        problem = path_problem(path) or "is not a regular file"
        raise ParamsError(f"params file {path} {problem}; give the path of a params YAML (e.g. params/sample.yaml)")
    return resolve_params(read_yaml_mapping(path), str(path), path.parent, **overrides)


def resolve_params(raw: dict[str, Any], source: str, folder: Path, **overrides: Any) -> dict[str, Any]:
    """``load_params`` of a mapping: errors name ``source`` (its ``params_file``), relative paths are
    read from ``folder``."""
    raw = dict(raw)
    given = {k: v for k, v in overrides.items() if v is not None}
    raw.update(given)
    params = {**OPTIONAL_KEYS, **raw, "params_file": source, "overridden": sorted(given)}
    _validate(params, source)
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
            registry.lookup("pairs_builder", params["pairs_builder"], dict.fromkeys(PAIR_BUILDER_NAMES))
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
        value = Path(_expand(str(value), source, key)).expanduser()
        params[key] = str(outputs_path(value if value.is_absolute() else real_path(folder / value)))
    if params["cache_dir"] is None:
        params["cache_dir"] = str(fetch.cache_dir())
    check_environment()
    return params


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
    folders = {"GVBENCH_DATA": "the data folder", "GVBENCH_CACHE": "the feature cache", "GVBENCH_OUTPUTS": "outputs/"}
    for name, what in folders.items():
        value = os.environ.get(name) or ""
        if "\0" in value or (value and Path(value).expanduser().is_file()):
            raise SettingError(
                f"the environment variable {name} ({what}) must name a folder, got {value!r}; fix or unset it"
            )


RESOLVED_PARAMS_NAME = "params.resolved.yaml"


def write_resolved_params(params: dict[str, Any], folder: Path, door: str = "python -m gvbench_nb run") -> Path:
    """The params a run uses, command-line overrides applied and paths absolute, as one YAML the
    notebooks load (``<run>/params.resolved.yaml``), headed by the file given (path, SHA-256) and ``door``."""
    keys = list(REQUIRED_KEYS) + list(OPTIONAL_KEYS)
    values = {key: params[key] for key in keys if key in params}
    source = params.get("params_file")  # params given in code (``run_method_of_params``) have no file
    if source and Path(source).is_file():
        source = f"{Path(source).resolve()} (sha256 {hashlib.sha256(Path(source).read_bytes()).hexdigest()})"
    header = (
        f"# The params this run used: {source} with the overrides given.\n"
        if source
        else "# The params this run used, given in code.\n"
    ) + f"# Written by `{door}`; every notebook of the run loads this file.\n"
    text = header + yaml.safe_dump(values, sort_keys=False, allow_unicode=True)
    return atomic_write_text(Path(folder) / RESOLVED_PARAMS_NAME, text)
