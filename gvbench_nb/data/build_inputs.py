"""What a retrieval-built sequence is made from: checked options, the traversals' images and metadata,
the ground-truth rule's parameters, and a digest of the inputs that says when a pair file is stale."""

from __future__ import annotations

import hashlib
import json
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Any

import numpy as np
import pandas as pd
from pydantic import BaseModel, BeforeValidator, ConfigDict, Field, StrictInt, ValidationError

from gvbench_nb import GVBenchError
from gvbench_nb.data import retrieval
from gvbench_nb.data.sequences import folder_images, frame_index
from gvbench_nb.io_utils import unknown_keys_hint
from gvbench_nb.protocol import registry
from gvbench_nb.protocol.images import IMAGE_EXTENSIONS

# Local features a vlad/bow descriptor aggregates -> the method whose extractor conf it
# reuses, so the feature cache is shared with that method's runs.
LOCAL_FEATURE_METHODS = {"sift": "sift-nn", "orb": "orb-nn"}


class BuildError(GVBenchError, ValueError):
    """Retrieval build options or inputs are wrong: says which, where, and what to do."""


# A name, or a list of names, as a tuple.
Names = Annotated[tuple[str, ...], BeforeValidator(lambda value: (value,) if isinstance(value, str) else value)]


class MetadataSpec(BaseModel):
    """Per-image metadata from a CSV (relative to image_root): ``name`` holds the image path
    relative to image_root or a bare file name inside the traversal's folder; ``frame``
    defaults to the number in the name (``sequences.frame_index``)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    csv: str
    name: str = "name"
    position: Annotated[Names, Field(min_length=1, max_length=3)] = ("x", "y")
    heading: str | None = "heading"
    frame: str | None = None


class RetrievalOptions(BaseModel):
    """The ``builder_options`` of ``pairs_builder: retrieval`` (docs/usage.md). Descriptor
    options are kept per descriptor name, so switching descriptor keeps each one's own;
    ``label_params_file`` (JSON, its mapping or its ``params``) yields to ``label_params``."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    query_folder: str
    reference_folders: Names
    descriptor: str = "vlad"
    descriptor_options: dict[str, dict[str, Any]] = {}
    local_features: str = "sift"
    feature_profile: str | None = None
    top_n: Annotated[StrictInt, Field(ge=1)] = 20
    num_queries: Annotated[StrictInt, Field(ge=1)] | None = None
    label_rule: str = "frame_tolerance"
    label_params: dict[str, Any] = {}
    label_params_file: str | None = None
    metadata: MetadataSpec | None = None
    render_sample: bool = False


def _refusal(errors: list[Any], raw: Mapping[str, Any]) -> str:
    """The one sentence (after ``where``) a user reads for pydantic's errors: unknown keys first."""
    error = next((e for e in errors if e["type"] == "extra_forbidden"), errors[0])
    key, loc = str(error["loc"][0]), error["loc"]
    if error["type"] == "extra_forbidden":
        model, place = (MetadataSpec, " metadata") if len(loc) > 1 else (RetrievalOptions, "")
        unknown = [str(e["loc"][-1]) for e in errors if e["type"] == "extra_forbidden" and e["loc"][:-1] == loc[:-1]]
        return f"{place}: unknown key(s) {unknown_keys_hint(unknown, list(model.model_fields))}; valid: {', '.join(model.model_fields)}"
    if error["type"] == "missing" and len(loc) == 1:
        return f": missing {key!r} (folders under image_root, e.g. night_right / [day_right])"
    if loc[:2] == ("metadata", "position"):
        return f": metadata position must name 1 to 3 columns, got {error['input']!r}"
    if key == "metadata" and (len(loc) == 1 or error["type"] == "missing"):
        return f": metadata must be null or a mapping with at least 'csv', got {raw[key]!r}"
    if key == "descriptor_options":
        got = f"{loc[1]!r}: {error['input']!r}" if len(loc) > 1 else repr(error["input"])
        return f": {DESCRIPTOR_OPTIONS_HINT}; got {got}"
    what = {"top_n": "a positive integer", "num_queries": "a positive integer or null"}.get(key)
    if what:
        return f": {key} must be {what}, got {raw[key]!r}"
    return f": {'.'.join(map(str, loc))}: {error['msg']}, got {error['input']!r}"


DESCRIPTOR_OPTIONS_HINT = (
    f"descriptor_options maps descriptor names ({', '.join(retrieval.GLOBAL_DESCRIPTORS)}) "
    "to their options, e.g. {vlad: {num_words: 64}}"
)


def parse_options(raw: Mapping[str, Any], where: str = "builder_options") -> RetrievalOptions:
    """Validated ``RetrievalOptions`` from a params file's ``builder_options``."""
    try:
        options = RetrievalOptions.model_validate(dict(raw))
    except ValidationError as error:
        raise BuildError(where + _refusal(error.errors(), raw)) from None
    if not options.reference_folders or len(set(options.reference_folders)) != len(options.reference_folders):
        raise BuildError(f"{where}: reference_folders must list distinct folders, got {raw['reference_folders']!r}")
    registry.lookup("descriptor", options.descriptor, retrieval.GLOBAL_DESCRIPTORS, where, error=BuildError)
    unknown = [name for name in options.descriptor_options if name not in retrieval.GLOBAL_DESCRIPTORS]
    if unknown:
        raise BuildError(f"{where}: {DESCRIPTOR_OPTIONS_HINT}; got {unknown[0]!r}")
    registry.check_choice("local_features", options.local_features, LOCAL_FEATURE_METHODS, where, error=BuildError)
    registry.lookup("label_rule", options.label_rule, retrieval.LABEL_RULES, where, error=BuildError)
    if options.query_folder in options.reference_folders:
        raise BuildError(f"{where}: the query folder {options.query_folder!r} is also a reference folder")
    return options


@dataclass(frozen=True)
class Traversal:
    """One image folder: names relative to image_root (sorted) and its frame table."""

    folder: str
    names: list[str]
    table: dict[str, np.ndarray]

    def rows(self, rows: np.ndarray) -> Traversal:
        """The traversal restricted to ``rows`` (in that order)."""
        return Traversal(self.folder, [self.names[i] for i in rows], {k: v[rows] for k, v in self.table.items()})


def list_images(image_root: Path, folder: str) -> list[str]:
    """Image paths ``folder/file`` relative to image_root, sorted."""
    directory = Path(image_root) / folder
    if not directory.is_dir():
        raise BuildError(f"image folder not found: {directory} (image_root {image_root}, folder {folder!r})")
    names = folder_images(image_root, folder)
    if not names:
        raise BuildError(f"no images ({', '.join(IMAGE_EXTENSIONS)}) in {directory}")
    return names


def _digest(path: Path, folder: bool, content_key: Callable[[Path], str]) -> str | None:
    """BLAKE2b of a folder's images' (or a file's) names and content keys; None when unreadable."""
    try:
        found = (
            sorted(p for p in path.iterdir() if p.suffix.lower() in IMAGE_EXTENSIONS and p.is_file())
            if folder
            else [path]
        )
        lines = [f"{p.name}\0{content_key(p)}\n" for p in found]
    except OSError:
        return None
    return hashlib.blake2b("".join(lines).encode(), digest_size=16).hexdigest()


def inputs_digest(
    image_root: str | Path, options: Mapping[str, Any], content_key: Callable[[Path], str]
) -> dict[str, str | None]:
    """A digest per image folder and per metadata or label_params file a build reads, by the files'
    ``content_key`` (the feature cache's), from the raw options, so a stale pair file shows before they are parsed."""
    references = options.get("reference_folders") or ()
    folders = [options.get("query_folder"), *([references] if isinstance(references, str) else references)]
    metadata = options.get("metadata")
    files = [metadata.get("csv") if isinstance(metadata, Mapping) else None, options.get("label_params_file")]
    named = [("folder", f) for f in folders] + [("file", f) for f in files]
    return {
        f"{kind}:{n}": _digest(Path(image_root) / n, kind == "folder", content_key)
        for kind, n in named
        if isinstance(n, str)
    }


def _frames_from_names(names: list[str]) -> np.ndarray | None:
    try:
        return np.array([frame_index(n) for n in names], dtype=np.int64)
    except ValueError:
        return None  # only a rule that reads frames needs them; it then says so


def _read_metadata(image_root: Path, spec: MetadataSpec) -> pd.DataFrame:
    path = Path(image_root) / spec.csv
    if not path.is_file():
        raise BuildError(f"metadata CSV not found: {path} (builder_options metadata.csv is relative to image_root)")
    table = pd.read_csv(path)
    wanted = [spec.name, *spec.position] + [c for c in (spec.heading, spec.frame) if c]
    missing = [c for c in wanted if c not in table.columns]
    if missing:
        raise BuildError(
            f"{path}: missing column(s) {missing}; it has {list(table.columns)} "
            "(set builder_options metadata.name/position/heading/frame to its column names)"
        )
    return table.set_index(table[spec.name].astype(str), drop=False)


def load_traversal(
    image_root: Path, folder: str, metadata: pd.DataFrame | None, spec: MetadataSpec | None
) -> Traversal:
    """A folder's images and their frame table (frames, and positions/headings from metadata)."""
    names = list_images(image_root, folder)
    frames = _frames_from_names(names)
    positions = headings = None
    if metadata is not None and spec is not None:
        # A CSV may name images relative to image_root or by file name inside the folder.
        keys = [n if n in metadata.index else n.split("/", 1)[1] for n in names]
        absent = [n for n, k in zip(names, keys) if k not in metadata.index]
        if absent:
            raise BuildError(
                f"{len(absent)} image(s) of {folder!r} have no row in the metadata CSV {spec.csv} "
                f"(column {spec.name!r}), e.g. {absent[:3]}"
            )
        rows = metadata.loc[keys]
        if len(rows) != len(names):  # a name on several rows (bare file names shared by traversals)
            raise BuildError(
                f"images of {folder!r} match several rows of the metadata CSV {spec.csv} (column {spec.name!r}); "
                "name each image once, by its path relative to image_root"
            )
        if spec.frame:
            frames = rows[spec.frame].to_numpy(np.int64)
        positions = rows[list(spec.position)].to_numpy(np.float64)
        headings = rows[spec.heading].to_numpy(np.float64) if spec.heading else None
    return Traversal(folder, names, retrieval.frame_table(names, frames, positions, headings))


def resolve_label_params(options: RetrievalOptions, image_root: Path) -> dict[str, Any]:
    """The rule's parameters: its defaults, then ``label_params_file``, then ``label_params``."""
    loaded: dict[str, Any] = {}
    if options.label_params_file:
        path = Path(image_root) / options.label_params_file
        if not path.is_file():
            raise BuildError(f"label_params_file not found: {path} (relative to image_root)")
        loaded = json.loads(path.read_text(encoding="utf-8"))
        defaults = retrieval.LABEL_RULES[options.label_rule].default_params
        loaded = {k: v for k, v in loaded.get("params", loaded).items() if k in defaults}
    try:
        return retrieval.rule_params(options.label_rule, {**loaded, **options.label_params})
    except KeyError as error:
        raise BuildError(error.args[0]) from None


@dataclass
class BuildInputs:
    """Everything a build needs, resolved from params: traversals, chosen queries and
    where local features live. ``local`` caches local descriptors once read."""

    params: dict[str, Any]
    options: RetrievalOptions
    image_root: Path
    query: Traversal  # the chosen query rows only
    num_query_frames: int
    experiences: dict[str, Traversal]
    rule_params: dict[str, Any]
    local: dict[str, np.ndarray] = field(default_factory=dict)

    @property
    def reference_names(self) -> list[str]:
        return [n for t in self.experiences.values() for n in t.names]

    def descriptor_options(self, descriptor: str) -> dict[str, Any]:
        return dict(self.options.descriptor_options.get(descriptor, {}))


def prepare_inputs(params: Mapping[str, Any], options: RetrievalOptions | None = None) -> BuildInputs:
    """Resolve a loaded params dict (``config.load_params``) into ``BuildInputs``."""
    options = options or parse_options(
        params.get("builder_options") or {}, f"{params.get('params_file', '<params>')}: builder_options"
    )
    image_root = Path(params["image_root"])
    if options.render_sample:
        from gvbench_nb.data import synthetic

        synthetic.generate_sample(image_root, seed=params.get("seed", 0))
    metadata = _read_metadata(image_root, options.metadata) if options.metadata else None
    query = load_traversal(image_root, options.query_folder, metadata, options.metadata)
    experiences = {f: load_traversal(image_root, f, metadata, options.metadata) for f in options.reference_folders}
    rows = retrieval.choose_queries(len(query.names), options.num_queries, params.get("seed", 0))
    rule_params = resolve_label_params(options, image_root)
    return BuildInputs(dict(params), options, image_root, query.rows(rows), len(query.names), experiences, rule_params)
