"""Build GV-Bench-style sequences from raw traversals: retrieval + a label rule.

GV-Bench made its pairs by mimicking a SLAM loop-closure detector: for each query
frame, retrieve the top N database frames by global-descriptor similarity (NetVLAD,
N = 20), then label every retrieved pair with a ground-truth rule. ``build_sequence``
does the same from image folders:

    query folder + reference folder(s) under image_root, per-image metadata
    -> chosen queries (all, or a seeded random subset)
    -> global descriptors (``retrieval.GLOBAL_DESCRIPTORS``: netvlad, vlad, bow;
       vlad/bow aggregate local features read from the package's feature cache)
    -> top-N candidates a query over every reference traversal ("experience")
    -> labels by a named rule (``retrieval.LABEL_RULES``)
    -> a GV-Bench pair file plus a sequence card beside it.

Files written for a pair file ``<stem>.txt``:

- ``<stem>.txt``: the pair file (``query reference label``), candidates of a query
  best first;
- ``<stem>.card.json`` / ``<stem>.card.md``: what was built and how (counts,
  positives a query, retrieval recall@1/5/N against the rule applied to every
  query x reference combination);
- ``<stem>.candidates.csv``: one row a pair with experience, rank, similarity, label.

Params (the ``builder_options`` of ``pairs_builder: retrieval``; see
``RetrievalOptions``), e.g.::

    pairs_builder: retrieval
    builder_options:
      query_folder: night_right
      reference_folders: [day_right]
      descriptor: vlad
      top_n: 10
      label_rule: frame_tolerance
      label_params: {k: 2}

Several reference traversals: every experience competes for the same N slots
(``retrieval.retrieve_top_n_experiences``), so a query's candidates may come from
any of them and the pair file lists them all. To score a query rather than a pair,
verify every candidate pair and keep, per query, the pair with the highest score
(``retrieval.best_experience``; ties go to the better retrieval rank): the query's
label is that pair's label (``best_experience_table`` joins a method's
``pairs.csv`` to the candidates for this).

``config`` imports this module to register the builder; this module never imports
``config`` (``pipeline`` is imported when features are extracted).
"""

from __future__ import annotations

import json
import time
from collections.abc import Mapping
from collections.abc import Sequence as SequenceType
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from gvbench_nb.data import retrieval
from gvbench_nb.data.sequences import (
    Pair,
    Sequence,
    frame_index,
    read_pairs,
    summarize,
    write_pairs,
)
from gvbench_nb.io_utils import atomic_write_csv, atomic_write_json, atomic_write_text
from gvbench_nb.protocol import registry

BUILDER_NAME = "retrieval"
IMAGE_EXTENSIONS = (".jpg", ".jpeg", ".png", ".ppm", ".bmp")
# Local features a vlad/bow descriptor aggregates -> the method whose extractor conf it
# reuses, so the feature cache is shared with that method's runs.
LOCAL_FEATURE_METHODS = {"sift": "sift-nn", "orb": "orb-nn"}
CANDIDATE_COLUMNS = ["query", "experience", "reference", "rank", "similarity", "label"]

MULTI_EXPERIENCE_NOTE = (
    "Every reference experience competes for the same top-N slots, so the pair file lists candidates from "
    "all of them. To score a query, verify every candidate pair and keep the pair with the highest score "
    "(retrieval.best_experience; ties go to the better retrieval rank); the query's label is that pair's label."
)


class BuildError(ValueError):
    """Retrieval build options or inputs are wrong: says which, where, and what to do."""


# ============================================================================ options


@dataclass(frozen=True)
class MetadataSpec:
    """Per-image metadata from a CSV (path relative to image_root), one row an image.

    ``name``: the column holding the image path relative to image_root (a bare file
    name is looked up inside the traversal's folder); ``position``: columns in metres
    (2 or 3); ``heading``: degrees (optional); ``frame``: a frame-number column
    (optional; default: parsed from the name, ``sequences.frame_index``).
    """

    csv: str
    name: str = "name"
    position: tuple[str, ...] = ("x", "y")
    heading: str | None = "heading"
    frame: str | None = None


@dataclass(frozen=True)
class RetrievalOptions:
    """The ``builder_options`` of ``pairs_builder: retrieval``.

    query_folder        folder (under image_root) of the query traversal
    reference_folders   one or more reference folders ("experiences")
    descriptor          a name in ``retrieval.GLOBAL_DESCRIPTORS``: netvlad, vlad, bow
    descriptor_options  {descriptor name: its keyword arguments}, e.g. {vlad: {num_words: 64}};
                        kept per name so that switching descriptor keeps each one's own
    local_features      vlad/bow only: 'sift' or 'orb' (the sift-nn / orb-nn extractor)
    feature_profile     profile of that extractor; null = the params' profile
    top_n               candidates a query (GV-Bench: 20)
    num_queries         null = every query frame, else a seeded random subset of that size
    label_rule          a name in ``retrieval.LABEL_RULES``: pose, frame_tolerance, manual
    label_params        the rule's parameters (override its defaults)
    label_params_file   JSON file (relative to image_root) whose mapping, or its
                        ``params`` mapping, supplies the rule parameters it names
                        (the sample's generator.json); label_params win
    metadata            null = frame numbers from the names, else a ``MetadataSpec`` mapping
    render_sample       render the embedded synthetic sample into image_root first
    """

    query_folder: str
    reference_folders: tuple[str, ...]
    descriptor: str = "vlad"
    descriptor_options: Mapping[str, Mapping[str, Any]] = field(default_factory=dict)
    local_features: str = "sift"
    feature_profile: str | None = None
    top_n: int = 20
    num_queries: int | None = None
    label_rule: str = "frame_tolerance"
    label_params: Mapping[str, Any] = field(default_factory=dict)
    label_params_file: str | None = None
    metadata: MetadataSpec | None = None
    render_sample: bool = False


def _unknown_keys(given: Mapping[str, Any], valid: SequenceType[str], where: str) -> None:
    unknown = [k for k in given if k not in valid]
    if unknown:
        raise BuildError(
            f"{where}: unknown key(s) {registry.unknown_keys_hint(unknown, list(valid))}; valid: {', '.join(valid)}"
        )


def _metadata_spec(raw: Any, where: str) -> MetadataSpec | None:
    if raw is None:
        return None
    if not isinstance(raw, Mapping) or "csv" not in raw:
        raise BuildError(f"{where}: metadata must be null or a mapping with at least 'csv', got {raw!r}")
    _unknown_keys(raw, list(MetadataSpec.__dataclass_fields__), f"{where} metadata")
    values = dict(raw)
    if "position" in values:
        position = values["position"]
        position = [position] if isinstance(position, str) else list(position)
        if not 1 <= len(position) <= 3:
            raise BuildError(f"{where}: metadata position must name 1 to 3 columns, got {position!r}")
        values["position"] = tuple(position)
    return MetadataSpec(**values)


def parse_options(raw: Mapping[str, Any], where: str = "builder_options") -> RetrievalOptions:
    """Validated ``RetrievalOptions`` from a params file's ``builder_options``."""
    _unknown_keys(raw, list(RetrievalOptions.__dataclass_fields__), where)
    for key in ("query_folder", "reference_folders"):
        if key not in raw:
            raise BuildError(f"{where}: missing {key!r} (folders under image_root, e.g. night_right / [day_right])")
    values = dict(raw)
    references = values["reference_folders"]
    values["reference_folders"] = (references,) if isinstance(references, str) else tuple(references)
    if not values["reference_folders"] or len(set(values["reference_folders"])) != len(values["reference_folders"]):
        raise BuildError(f"{where}: reference_folders must list distinct folders, got {references!r}")
    values["metadata"] = _metadata_spec(values.get("metadata"), where)
    options = RetrievalOptions(**values)
    registry.lookup("descriptor", options.descriptor, retrieval.GLOBAL_DESCRIPTORS, where, error=BuildError)
    for name, descriptor_conf in options.descriptor_options.items():
        if name not in retrieval.GLOBAL_DESCRIPTORS or not isinstance(descriptor_conf, Mapping):
            raise BuildError(
                f"{where}: descriptor_options maps descriptor names ({', '.join(retrieval.GLOBAL_DESCRIPTORS)}) "
                f"to their options, e.g. {{vlad: {{num_words: 64}}}}; got {name!r}: {descriptor_conf!r}"
            )
    if options.local_features not in LOCAL_FEATURE_METHODS:
        raise BuildError(
            f"{where}: local_features must be one of {', '.join(LOCAL_FEATURE_METHODS)}, got {options.local_features!r}"
        )
    registry.lookup("label_rule", options.label_rule, retrieval.LABEL_RULES, where, error=BuildError)
    if not isinstance(options.top_n, int) or isinstance(options.top_n, bool) or options.top_n < 1:
        raise BuildError(f"{where}: top_n must be a positive integer, got {options.top_n!r}")
    if options.num_queries is not None and (not isinstance(options.num_queries, int) or options.num_queries < 1):
        raise BuildError(f"{where}: num_queries must be a positive integer or null, got {options.num_queries!r}")
    if options.query_folder in options.reference_folders:
        raise BuildError(f"{where}: the query folder {options.query_folder!r} is also a reference folder")
    return options


# ============================================================================ traversals


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
    names = sorted(f"{folder}/{p.name}" for p in directory.iterdir() if p.suffix.lower() in IMAGE_EXTENSIONS)
    if not names:
        raise BuildError(f"no images ({', '.join(IMAGE_EXTENSIONS)}) in {directory}")
    return names


def inputs_digest(image_root: str | Path, options: Mapping[str, Any]) -> dict[str, str | None]:
    """What a retrieval build read, as one BLAKE2b digest a file or folder: each image
    folder's listing (every image's name, size, mtime and inode: the pipeline's rule for when
    a file is hashed again), the metadata CSV and the label_params_file. A frame added,
    removed or replaced changes its folder's digest. Read from the raw options, so a stamp
    can be compared before they are parsed; a folder or file that is not there is None."""
    import hashlib
    import os

    def digest(entries: list[tuple[str, os.stat_result]]) -> str:
        blake = hashlib.blake2b(digest_size=16)
        for name, info in sorted(entries, key=lambda entry: entry[0]):
            blake.update(f"{name}\0{info.st_size}\0{info.st_mtime_ns}\0{info.st_ino}\n".encode())
        return blake.hexdigest()

    def folder_digest(folder: Path) -> str | None:
        try:
            with os.scandir(folder) as listing:
                entries = [
                    (entry.name, entry.stat())
                    for entry in listing
                    if Path(entry.name).suffix.lower() in IMAGE_EXTENSIONS and entry.is_file()
                ]
        except OSError:
            return None
        return digest(entries)

    def file_digest(path: Path) -> str | None:
        try:
            return digest([(path.name, path.stat())])
        except OSError:
            return None

    root = Path(image_root)
    references = options.get("reference_folders") or ()
    folders = [options.get("query_folder"), *([references] if isinstance(references, str) else references)]
    found: dict[str, str | None] = {
        f"folder:{folder}": folder_digest(root / folder) for folder in folders if isinstance(folder, str)
    }
    metadata = options.get("metadata")
    for name in (metadata.get("csv") if isinstance(metadata, Mapping) else None, options.get("label_params_file")):
        if isinstance(name, str):
            found[f"file:{name}"] = file_digest(root / name)
    return found


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
    if metadata is None or spec is None:
        table = retrieval.frame_table(names, frames if frames is not None else np.arange(len(names)))
        if frames is None:
            del table["frame"]
        return Traversal(folder, names, table)
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
    table = retrieval.frame_table(
        names,
        frames if frames is not None else np.arange(len(names)),
        positions=rows[list(spec.position)].to_numpy(np.float64),
        headings=rows[spec.heading].to_numpy(np.float64) if spec.heading else None,
    )
    if frames is None:
        del table["frame"]
    return Traversal(folder, names, table)


def resolve_label_params(options: RetrievalOptions, image_root: Path) -> dict[str, Any]:
    """The rule's parameters: its defaults, then ``label_params_file``, then ``label_params``."""
    rule = retrieval.get_label_rule(options.label_rule)
    merged = dict(rule.default_params)
    if options.label_params_file:
        path = Path(image_root) / options.label_params_file
        if not path.is_file():
            raise BuildError(f"label_params_file not found: {path} (relative to image_root)")
        loaded = json.loads(path.read_text(encoding="utf-8"))
        loaded = loaded.get("params", loaded)
        merged.update({k: v for k, v in loaded.items() if k in rule.default_params})
    unknown = set(options.label_params) - set(rule.default_params)
    if unknown:
        raise BuildError(
            f"label rule {rule.name!r} has no parameter(s) {sorted(unknown)}; known: {sorted(rule.default_params)}"
        )
    merged.update(options.label_params)
    return merged


# ============================================================================ descriptors


@dataclass
class BuildInputs:
    """Everything a build needs, resolved from params: traversals, chosen queries and
    where local features live. ``local`` caches local descriptors once read."""

    params: dict[str, Any]
    options: RetrievalOptions
    image_root: Path
    query: Traversal  # the chosen query rows only
    query_rows: np.ndarray  # their rows in the full query traversal
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
    return BuildInputs(
        dict(params),
        options,
        image_root,
        query.rows(rows),
        rows,
        len(query.names),
        experiences,
        resolve_label_params(options, image_root),
    )


def local_feature_conf(options: RetrievalOptions, profile: str) -> dict[str, Any]:
    """The extractor conf of ``local_features`` (identical to its method's, so the cache is shared)."""
    from gvbench_nb import methods

    return methods.resolve_method(LOCAL_FEATURE_METHODS[options.local_features], options.feature_profile or profile)[
        "extractor"
    ]


def load_local_descriptors(
    inputs: BuildInputs, names: SequenceType[str], progress: bool = True
) -> dict[str, np.ndarray]:
    """Local descriptors ``{name: (N, D)}`` from the feature cache, extracting missing images first."""
    from gvbench_nb.runner import image_features

    todo = [n for n in names if n not in inputs.local]
    if todo:
        conf = local_feature_conf(inputs.options, inputs.params["profile"])
        cache_dir = Path(inputs.params["cache_dir"])
        # The pipeline extracts the images of a sequence's pairs: one self-pair an image lists them.
        listing = Sequence(inputs.params.get("sequence", "build"), inputs.image_root, [Pair(n, n, 0) for n in todo])
        image_features.extract_features(listing, conf, cache_dir, inputs.params.get("device", "auto"), progress)
        store = image_features.feature_store(cache_dir, conf)
        store.refresh()
        for name in todo:
            inputs.local[name] = store.read(image_features.image_key(inputs.image_root, name))["descriptors"]
        store.close()
    return {n: inputs.local[n] for n in names}


def global_descriptors(
    inputs: BuildInputs, descriptor: str, descriptor_options: Mapping[str, Any] | None = None, progress: bool = True
) -> retrieval.GlobalDescriptors:
    """Rows for the chosen queries and every reference (experiences in order, stacked).

    vlad/bow fit their vocabulary on all reference experiences together (the map)."""
    method = registry.lookup("descriptor", descriptor, retrieval.GLOBAL_DESCRIPTORS, error=BuildError)
    options = dict(descriptor_options or {})
    references, queries = inputs.reference_names, inputs.query.names
    if method.inputs == "images":
        from gvbench_nb.protocol.features.base import resolve_device

        device = str(resolve_device(inputs.params.get("device", "auto")))
        paths = lambda names: {n: str(inputs.image_root / n) for n in names}
        return retrieval.compute_global_descriptors(
            descriptor, paths(references), paths(queries), device=device, **options
        )
    local = load_local_descriptors(inputs, list(references) + list(queries), progress)
    return retrieval.compute_global_descriptors(
        descriptor,
        {n: local[n] for n in references},
        {n: local[n] for n in queries},
        seed=inputs.params.get("seed", 0),
        **options,
    )


# ============================================================================ retrieval + labels


def ground_truth(inputs: BuildInputs) -> np.ndarray:
    """(Q, R) bool: the rule on every chosen query x every reference (experiences stacked)."""
    blocks = [
        retrieval.ground_truth_matrix(inputs.options.label_rule, inputs.rule_params, inputs.query.table, t.table)
        for t in inputs.experiences.values()
    ]
    return np.concatenate(blocks, axis=1)


def retrieve(inputs: BuildInputs, descriptors: retrieval.GlobalDescriptors, n: int) -> retrieval.Candidates:
    """Top-n candidates a chosen query over every experience."""
    rows: dict[str, np.ndarray] = {}
    start = 0
    for folder, traversal in inputs.experiences.items():
        rows[folder] = descriptors.reference[start : start + len(traversal.names)]
        start += len(traversal.names)
    return retrieval.retrieve_top_n_experiences(descriptors.query, rows, n)


def stacked_indices(inputs: BuildInputs, candidates: retrieval.Candidates) -> np.ndarray:
    """(Q, n) candidate columns in the stacked reference order of ``ground_truth``."""
    offsets, start = {}, 0
    for folder, traversal in inputs.experiences.items():
        offsets[folder] = start
        start += len(traversal.names)
    columns = np.array([offsets[e] for e in candidates.experience], dtype=np.int64) + candidates.reference
    return columns.reshape(len(inputs.query.names), -1)


def label_candidates(inputs: BuildInputs, candidates: retrieval.Candidates) -> np.ndarray:
    """(P,) labels of candidate pairs, by the rule applied experience by experience."""
    labels = np.zeros(len(candidates), dtype=bool)
    for folder, traversal in inputs.experiences.items():
        mine = candidates.experience == folder
        pairs = np.stack([candidates.query[mine], candidates.reference[mine]], axis=1)
        labels[mine] = retrieval.label_pairs(
            inputs.options.label_rule, inputs.rule_params, inputs.query.table, traversal.table, pairs
        )
    return labels


def candidate_frame(inputs: BuildInputs, candidates: retrieval.Candidates, labels: np.ndarray) -> pd.DataFrame:
    """One row a candidate pair with image names: query, experience, reference, rank, similarity, label."""
    return pd.DataFrame(
        {
            "query": [inputs.query.names[q] for q in candidates.query],
            "experience": candidates.experience.astype(str),
            "reference": [inputs.experiences[e].names[r] for e, r in zip(candidates.experience, candidates.reference)],
            "rank": candidates.rank,
            "similarity": candidates.similarity,
            "label": labels.astype(int),
        },
        columns=CANDIDATE_COLUMNS,
    )


def recall_ks(top_n: int) -> list[int]:
    """The card's recall@k: 1, 5 and N (those <= N)."""
    return sorted({k for k in (1, 5, top_n) if k <= top_n})


# ============================================================================ card


def card_paths(pairs_path: str | Path) -> dict[str, Path]:
    """Files written beside a pair file ``<stem>.txt``."""
    pairs_path = Path(pairs_path)
    stem = pairs_path.with_suffix("")
    return {
        "pairs": pairs_path,
        "card_json": Path(f"{stem}.card.json"),
        "card_markdown": Path(f"{stem}.card.md"),
        "candidates": Path(f"{stem}.candidates.csv"),
    }


def make_card(
    inputs: BuildInputs,
    frame: pd.DataFrame,
    truth: np.ndarray,
    recall: dict[str, float],
    seconds: dict[str, float],
    files: dict[str, Path],
    feature_conf: dict[str, Any] | None,
) -> dict[str, Any]:
    """The sequence card: how the pairs were made, and counts computed from the pairs written."""
    from gvbench_nb.methods import conf_hash

    options = inputs.options
    pairs = [Pair(q, r, int(label)) for q, r, label in zip(frame["query"], frame["reference"], frame["label"])]
    counts = summarize(Sequence(inputs.params.get("sequence", "build"), inputs.image_root, pairs))
    per_experience = {
        e: {
            "n_pairs": int((frame["experience"] == e).sum()),
            "n_positives": int(frame.loc[frame["experience"] == e, "label"].sum()),
        }
        for e in inputs.experiences
    }
    return {
        "sequence": inputs.params.get("sequence"),
        "builder": BUILDER_NAME,
        "params_file": inputs.params.get("params_file"),
        "image_root": str(inputs.image_root),
        "query_traversal": options.query_folder,
        "reference_traversals": list(options.reference_folders),
        "query_frames": inputs.num_query_frames,
        "reference_frames": {e: len(t.names) for e, t in inputs.experiences.items()},
        "num_queries_requested": options.num_queries,
        "seed": inputs.params.get("seed", 0),
        "descriptor": options.descriptor,
        "descriptor_options": inputs.descriptor_options(options.descriptor),
        "local_features": None
        if feature_conf is None
        else {
            "extractor": feature_conf["name"],
            "profile": options.feature_profile or inputs.params["profile"],
            "conf_hash": conf_hash(feature_conf),
            "shared_with_method": LOCAL_FEATURE_METHODS[options.local_features],
        },
        "top_n": options.top_n,
        "label_rule": options.label_rule,
        "label_params": inputs.rule_params,
        "counts": {k: v for k, v in counts.items() if k != "sequence"},
        "per_experience": per_experience,
        "ground_truth": {
            "true_references_per_query": float(truth.sum(1).mean()) if len(truth) else 0.0,
            "queries_without_true_reference": int((~truth.any(1)).sum()),
        },
        "retrieval_recall": recall,
        "multi_experience_scoring": MULTI_EXPERIENCE_NOTE,
        "files": {k: str(v) for k, v in files.items()},
        "seconds": seconds,
    }


def card_markdown(card: Mapping[str, Any]) -> str:
    """A short human-readable card (what ``python -m gvbench_nb build`` prints)."""
    counts, recall = card["counts"], card["retrieval_recall"]
    features = card["local_features"]
    feature_text = f", local features {features['extractor']} ({features['profile']})" if features else ""
    lines = [
        f"# Sequence card: {card['sequence']}",
        "",
        f"Queries `{card['query_traversal']}` ({counts['n_queries']} of {card['query_frames']} frames) against "
        f"{', '.join(f'`{e}`' for e in card['reference_traversals'])}; top {card['top_n']} by "
        f"{card['descriptor']}{feature_text}; labels by rule `{card['label_rule']}` {json.dumps(card['label_params'])}; "
        f"seed {card['seed']}.",
        "",
        "| quantity | value |",
        "|---|---|",
        f"| queries | {counts['n_queries']} |",
        f"| pairs | {counts['n_pairs']} |",
        f"| positives | {counts['n_positives']} |",
        f"| positives a query | {counts['positives_per_query']:.2f} |",
        f"| queries without a positive | {counts['queries_without_positive']} |",
        f"| true references a query (ground truth) | {card['ground_truth']['true_references_per_query']:.2f} |",
        f"| queries without any true reference | {card['ground_truth']['queries_without_true_reference']} |",
    ]
    lines += [f"| retrieval {k} | {v:.3f} |" for k, v in recall.items() if k.startswith("recall@")]
    if len(card["per_experience"]) > 1:
        lines += [
            f"| pairs / positives from `{e}` | {v['n_pairs']} / {v['n_positives']} |"
            for e, v in card["per_experience"].items()
        ]
    lines += [
        "",
        f"Recall@k: fraction of the {recall['queries_evaluated']} queries with a true reference anywhere "
        f"({recall['queries_excluded']} without one are excluded) that have one among their top k.",
        "",
        f"Files: `{Path(card['files']['pairs']).name}` (pairs), `{Path(card['files']['candidates']).name}` (ranks, similarities).",
    ]
    if len(card["per_experience"]) > 1:
        lines += ["", card["multi_experience_scoring"]]
    return "\n".join(lines) + "\n"


# ============================================================================ entry points


def build_sequence(build_params: Mapping[str, Any], progress: bool = True) -> dict[str, Any]:
    """Build the pair file of a loaded params dict (``pairs_builder: retrieval``) and
    its card; returns the card. Overwrites ``build_params['pairs']`` and the card files."""
    inputs = prepare_inputs(build_params)
    options = inputs.options
    started = time.perf_counter()
    descriptors = global_descriptors(
        inputs, options.descriptor, inputs.descriptor_options(options.descriptor), progress
    )
    described = time.perf_counter()
    candidates = retrieve(inputs, descriptors, options.top_n)
    labels = label_candidates(inputs, candidates)
    truth = ground_truth(inputs)
    recall = retrieval.retrieval_recall_at(
        recall_ks(min(options.top_n, truth.shape[1])), stacked_indices(inputs, candidates), truth
    )
    retrieved = time.perf_counter()
    frame = candidate_frame(inputs, candidates, labels)
    files = card_paths(build_params["pairs"])
    write_pairs(files["pairs"], zip(frame["query"], frame["reference"], frame["label"]))
    feature_conf = (
        local_feature_conf(options, build_params["profile"])
        if retrieval.GLOBAL_DESCRIPTORS[options.descriptor].inputs == "local_descriptors"
        else None
    )
    card = make_card(
        inputs,
        frame,
        truth,
        recall,
        {"descriptors": described - started, "retrieval_and_labels": retrieved - described},
        files,
        feature_conf,
    )
    atomic_write_csv(files["candidates"], frame)
    atomic_write_json(files["card_json"], card)
    atomic_write_text(files["card_markdown"], card_markdown(card))
    return card


def build_retrieval_pairs(params: dict[str, Any]) -> None:
    """``config.PAIR_BUILDERS['retrieval']``: writes ``params['pairs']`` (and the card)."""
    build_sequence(params)


# ============================================================================ params + CLI


def read_card(pairs_path: str | Path) -> dict[str, Any]:
    return json.loads(card_paths(pairs_path)["card_json"].read_text(encoding="utf-8"))


def check_card(pairs_path: str | Path) -> None:
    """Raise when a card's counts disagree with its pair file (e.g. the file was edited)."""
    card = read_card(pairs_path)
    counts = summarize(Sequence(card["sequence"] or "build", Path("."), read_pairs(pairs_path)))
    wrong = {k: (card["counts"][k], v) for k, v in counts.items() if k != "sequence" and card["counts"].get(k) != v}
    if wrong:
        raise BuildError(f"{pairs_path}: card counts differ from the pair file (card, file): {wrong}; rebuild it")


# ============================================================================ figures
