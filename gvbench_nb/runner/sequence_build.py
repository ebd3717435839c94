"""A params file's sequence, its pairs made by its builder when one is set. The retrieval builder
proposes pairs as a SLAM loop-closure detector would: each query's top-N references over every
reference traversal, labelled by a rule, with a card (``<stem>.card.json``/``.md``) beside."""

from __future__ import annotations

import json
import os
import time
from collections.abc import Callable, Mapping
from collections.abc import Sequence as SequenceType
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from gvbench_nb.data import build_inputs, fetch, retrieval, sequences
from gvbench_nb.data.sequences import Pair, Sequence, frame_tolerance_pairs, read_pairs, summarize, write_pairs
from gvbench_nb.io_utils import atomic_write_csv, atomic_write_json, atomic_write_text, file_sha256
from gvbench_nb.protocol import registry
from gvbench_nb.protocol.images import path_problem
from gvbench_nb.runner import config, image_features

BUILDER_NAME = "retrieval"
MULTI_EXPERIENCE_NOTE = (
    "Every reference experience competes for the same top-N slots, so the pair file lists candidates from "
    "all of them. To score a query, verify every candidate pair and keep the pair with the highest score "
    "(gvbench_nb.studies.build_sequence.best_experience_table; ties go to the better retrieval rank); "
    "the query's label is that pair's label."
)


def local_feature_conf(options: build_inputs.RetrievalOptions, profile: str) -> dict[str, Any]:
    """The extractor conf of ``local_features`` (identical to its method's, so the cache is shared)."""
    from gvbench_nb import methods

    return methods.resolve_method(
        build_inputs.LOCAL_FEATURE_METHODS[options.local_features], options.feature_profile or profile
    )["extractor"]


def load_local_descriptors(
    inputs: build_inputs.BuildInputs, names: SequenceType[str], progress: bool = True
) -> dict[str, np.ndarray]:
    """Local descriptors ``{name: (N, D)}`` from the feature cache, extracting missing images first."""
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
    inputs: build_inputs.BuildInputs,
    descriptor: str,
    descriptor_options: Mapping[str, Any] | None = None,
    progress: bool = True,
) -> tuple[np.ndarray, np.ndarray]:
    """Rows (reference, query): every reference, experiences stacked (vlad/bow fit on them all), and the chosen queries."""
    compute = registry.lookup("descriptor", descriptor, retrieval.GLOBAL_DESCRIPTORS, error=build_inputs.BuildError)
    options = dict(descriptor_options or {})
    references, queries = inputs.reference_names, inputs.query.names
    if descriptor in retrieval.IMAGE_DESCRIPTORS:
        from gvbench_nb.protocol.features.base import resolve_device

        device = str(resolve_device(inputs.params.get("device", "auto")))
        paths = lambda names: {n: str(inputs.image_root / n) for n in names}
        return compute(paths(references), paths(queries), device=device, **options)
    local = load_local_descriptors(inputs, [*references, *queries], progress)
    seed = inputs.params.get("seed", 0)
    return compute({n: local[n] for n in references}, {n: local[n] for n in queries}, seed=seed, **options)


def ground_truth(inputs: build_inputs.BuildInputs) -> np.ndarray:
    """(Q, R) bool: the rule on every chosen query x every reference (experiences stacked)."""
    blocks = [
        retrieval.ground_truth_matrix(inputs.options.label_rule, inputs.rule_params, inputs.query.table, t.table)
        for t in inputs.experiences.values()
    ]
    return np.concatenate(blocks, axis=1)


def candidate_frame(
    inputs: build_inputs.BuildInputs, indices: np.ndarray, similarities: np.ndarray, truth: np.ndarray
) -> pd.DataFrame:
    """One row a retrieved pair (query, experience, reference, rank, similarity, label), ``indices`` and
    ``truth`` over the stacked references: every experience competes for the same top-N slots."""
    experiences = np.repeat(list(inputs.experiences), [len(t.names) for t in inputs.experiences.values()])
    columns = indices.reshape(-1)
    return pd.DataFrame(
        {
            "query": np.repeat(inputs.query.names, indices.shape[1]),
            "experience": experiences[columns],
            "reference": np.asarray(inputs.reference_names)[columns],
            "rank": np.tile(np.arange(indices.shape[1]), len(indices)),
            "similarity": similarities.reshape(-1),
            "label": np.take_along_axis(truth, indices, axis=1).reshape(-1).astype(int),
        }
    )


def card_paths(pairs_path: str | Path) -> dict[str, Path]:
    """Files written beside a pair file ``<stem>.txt``."""
    stem = Path(pairs_path).with_suffix("")
    beside = {"card_json": "card.json", "card_markdown": "card.md", "candidates": "candidates.csv"}
    return {"pairs": Path(pairs_path)} | {key: Path(f"{stem}.{suffix}") for key, suffix in beside.items()}


def make_card(
    inputs: build_inputs.BuildInputs,
    frame: pd.DataFrame,
    pairs: list[Pair],
    truth: np.ndarray,
    recall: dict[str, float],
    seconds: dict[str, float],
    files: dict[str, Path],
) -> dict[str, Any]:
    """The sequence card: how the pairs were made, and counts computed from the pairs written."""
    from gvbench_nb.methods import conf_hash

    options = inputs.options
    local_features = None
    if options.descriptor not in retrieval.IMAGE_DESCRIPTORS:
        feature_conf = local_feature_conf(options, inputs.params["profile"])
        local_features = {
            "extractor": feature_conf["name"],
            "profile": options.feature_profile or inputs.params["profile"],
            "conf_hash": conf_hash(feature_conf),
            "shared_with_method": build_inputs.LOCAL_FEATURE_METHODS[options.local_features],
        }
    counts = summarize(Sequence(inputs.params.get("sequence", "build"), inputs.image_root, pairs))
    by_experience = frame.groupby("experience")["label"].agg(n_pairs="size", n_positives="sum")
    per_experience = by_experience.reindex(list(inputs.experiences), fill_value=0).to_dict("index")
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
        "local_features": local_features,
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


def build_sequence(build_params: Mapping[str, Any], progress: bool = True) -> dict[str, Any]:
    """Write the pair file and card of a ``pairs_builder: retrieval`` params dict; returns the card."""
    inputs = build_inputs.prepare_inputs(build_params)
    options = inputs.options
    started = time.perf_counter()
    reference, query = global_descriptors(
        inputs, options.descriptor, inputs.descriptor_options(options.descriptor), progress
    )
    described = time.perf_counter()
    indices, similarities = retrieval.retrieve_top_n(query, reference, options.top_n)
    truth = ground_truth(inputs)
    top_n = indices.shape[1]
    ks = sorted({k for k in (1, 5, top_n) if k <= top_n})  # the card's recall@1, 5 and N
    recall = retrieval.retrieval_recall_at(ks, indices, truth)
    retrieved = time.perf_counter()
    frame = candidate_frame(inputs, indices, similarities, truth)
    files = card_paths(build_params["pairs"])
    pairs = [Pair(q, r, int(label)) for q, r, label in zip(frame["query"], frame["reference"], frame["label"])]
    write_pairs(files["pairs"], pairs)
    seconds = {"descriptors": described - started, "retrieval_and_labels": retrieved - described}
    card = make_card(inputs, frame, pairs, truth, recall, seconds, files)
    atomic_write_csv(files["candidates"], frame)
    atomic_write_json(files["card_json"], card)
    atomic_write_text(files["card_markdown"], card_markdown(card))
    return card


def check_card(pairs_path: str | Path) -> None:
    """Raise when a card's counts disagree with its pair file (e.g. the file was edited)."""
    card = json.loads(card_paths(pairs_path)["card_json"].read_text(encoding="utf-8"))
    counts = summarize(Sequence(card["sequence"] or "build", Path("."), read_pairs(pairs_path)))
    wrong = {k: (card["counts"][k], v) for k, v in counts.items() if k != "sequence" and card["counts"].get(k) != v}
    if wrong:
        raise build_inputs.BuildError(
            f"{pairs_path}: card counts differ from the pair file (card, file): {wrong}; rebuild it"
        )


def load_build_params(
    params_file: str | Path, descriptor: str | None = None, top_n: int | None = None, **overrides: Any
) -> dict[str, Any]:
    """``load_params`` of a ``pairs_builder: retrieval`` file, with build overrides."""
    params = config.load_params(params_file, **overrides)
    if params["pairs_builder"] != BUILDER_NAME:
        raise build_inputs.BuildError(
            f"{params['params_file']}: pairs_builder is {params['pairs_builder']!r}; "
            f"building needs pairs_builder: {BUILDER_NAME} with its builder_options"
        )
    options = dict(params["builder_options"])
    options.update({k: v for k, v in (("descriptor", descriptor), ("top_n", top_n)) if v is not None})
    build_inputs.parse_options(options, f"{params['params_file']}: builder_options")  # fail before any work
    params["builder_options"] = options
    return params


def build_sample(params: dict[str, Any]) -> None:
    """The embedded default: a synthetic route rendered by the package (seconds, no download)."""
    from gvbench_nb.data import synthetic

    synthetic.generate_sample(Path(params["image_root"]), seed=params["seed"], **params["builder_options"])


def frame_tolerance_sequence_pairs(params: dict[str, Any]) -> list[Pair]:
    """The pairs the frame_tolerance builder makes of the params' two image folders."""
    options = dict(params["builder_options"])
    root = Path(params["image_root"])
    query_folder = options.pop("query_folder")
    reference_folder = options.pop("reference_folder")

    def names(folder: str) -> list[str]:
        directory = root / folder
        if not directory.is_dir():
            raise config.ParamsError(
                f"{params['params_file']}: image folder {directory} not found (image_root {root}, folder {folder!r})"
                + (fetch.fetch_hint(directory) or "; set image_root to the folder holding it")
            )
        return sequences.folder_images(root, folder)

    try:
        return frame_tolerance_pairs(names(query_folder), names(reference_folder), seed=params["seed"], **options)
    except (TypeError, ValueError) as error:
        raise config.ParamsError(f"{params['params_file']}: builder_options: {error}") from None


def build_frame_tolerance(params: dict[str, Any]) -> None:
    """Rule-built pairs of a frame-aligned sequence (see ``sequences.frame_tolerance_pairs``)."""
    pairs = frame_tolerance_sequence_pairs(params)
    # Rebuilt on every run (milliseconds, seeded): a pair file made under other options is
    # replaced, and an unchanged one is left untouched.
    if not Path(params["pairs"]).is_file() or read_pairs(params["pairs"]) != pairs:
        write_pairs(params["pairs"], pairs)


PAIR_BUILDERS: dict[str, Callable[[dict[str, Any]], object]] = {  # config.PAIR_BUILDER_NAMES
    "sample": build_sample,
    "frame_tolerance": build_frame_tolerance,
    BUILDER_NAME: build_sequence,  # GV-Bench's way (build.py): top-N retrieval, labelled by a rule
}


def builder_stamp_path(pairs: str | os.PathLike[str]) -> Path:
    """``<pairs>.builder.json``: what built a pair file (builder, options, seed, image root)."""
    pairs = Path(pairs)
    return pairs.with_name(pairs.name + ".builder.json")


def builder_stamp(params: dict[str, Any]) -> dict[str, Any]:
    """What a builder's output depends on, as JSON reads it back (retrieval: also what it read there)."""
    stamp = {key: params[key] for key in ("pairs_builder", "builder_options", "seed", "image_root")}
    if params["pairs_builder"] == BUILDER_NAME and params["image_root"] is not None:
        stamp["inputs"] = build_inputs.inputs_digest(
            params["image_root"], params["builder_options"], image_features.content_key
        )
    return json.loads(json.dumps(stamp, sort_keys=True, default=str))


def _stamp_matches(params: dict[str, Any]) -> bool:
    """The pair file was built by this builder, with these options and seed, and not changed since."""
    pairs = Path(params["pairs"])
    try:
        recorded = dict(json.loads(builder_stamp_path(pairs).read_text(encoding="utf-8")))
    except (OSError, ValueError, TypeError):
        return False
    if not pairs.is_file():
        return False
    sha256 = recorded.pop("pairs_sha256", None)
    return recorded == builder_stamp(params) and sha256 == file_sha256(pairs)


def missing_pairs_error(params: dict[str, Any]) -> config.ParamsError:
    pairs = Path(params["pairs"])
    what = path_problem(pairs) or "is not a pair file"
    what = "is a folder, not a pair file" if what == "is a folder, not a file" else what
    return config.ParamsError(
        f"{params['params_file']}: the pair file {pairs} {what}; set pairs to a file of "
        "'query_path reference_path label' lines, or set pairs_builder to make it"
    )


def check_image_root(params: dict[str, Any]) -> Path:
    """The image root, refused when unset, or (unless the sample builder renders it) not a folder."""
    source = config.blame(params, "image_root")
    if params["image_root"] is None:
        raise config.ParamsError(
            f"{source}: image_root is not set. Set it (or pass --image-root) to the folder holding the images "
            f"that the pair file's paths are relative to (e.g. the GV-Bench image root with day0/, night0/, ...)"
        )
    root = Path(params["image_root"])
    renders = params["pairs_builder"] == "sample" or (
        params["pairs_builder"] == BUILDER_NAME and params["builder_options"].get("render_sample")
    )
    if renders and "image_root" in params["overridden"] and not (root / "generator.json").is_file():
        # A folder typed on the command line names images; a builder renders only into the params file's.
        what = "holds no rendered route" if root.is_dir() else "does not exist"
        raise config.ParamsError(
            f"--image-root {root} {what}: a folder given on the command line must hold the images, it is never "
            f"rendered into; drop --image-root to render into the params file's image_root, or set image_root "
            f"in a params file of your own (its pairs_builder renders the route there)"
        )
    if params["pairs_builder"] != "sample" and not root.is_dir():  # the sample builder renders into the root
        what = path_problem(root) or "is a file, not a folder"
        raise config.ParamsError(
            f"{source}: image_root {root} {what}"
            + (
                fetch.fetch_hint(root)
                or "; set image_root (or pass --image-root) to the folder "
                "holding the images that the pair file's paths are relative to"
            )
        )
    return root


def prepare_sequence(params: dict[str, Any]) -> Sequence:
    """The sequence of a params file. A builder's pair file is its own: rebuilt whenever its stamp
    (``<pairs>.builder.json``) differs from ``builder_stamp`` or the file changed since."""
    root = check_image_root(params)
    image_features.reuse_saved_keys(params["cache_dir"])  # no image another process hashed is hashed again
    builder = params["pairs_builder"]
    if builder and (builder == "sample" or not _stamp_matches(params)):
        builder_stamp_path(params["pairs"]).unlink(missing_ok=True)  # a killed build then rebuilds
        PAIR_BUILDERS[builder](params)
        atomic_write_json(
            builder_stamp_path(params["pairs"]), {**builder_stamp(params), "pairs_sha256": file_sha256(params["pairs"])}
        )
    if path_problem(params["pairs"]) is not None:
        raise missing_pairs_error(params)
    sequence = Sequence(params["sequence"], root, read_pairs(params["pairs"]), origin=sequence_origin(params))
    return sequence.limited(params["limit"])


def sequence_origin(params: dict[str, Any]) -> dict[str, Any]:
    """Where a sequence's pairs came from, as run.json records it (its image root and seed at its top)."""
    return {
        "params_file": params["params_file"],
        "pairs_file": params["pairs"],
        "pairs_sha256": file_sha256(params["pairs"]),
        "pairs_builder": params["pairs_builder"],
        "builder_options": params["builder_options"],
        "limit": params["limit"],
    }
