"""Build GV-Bench-style sequences from raw traversals, as a SLAM loop-closure detector would
propose them: each query's top-N references by a global descriptor over every reference
traversal ("experience", all competing for the same N slots), labelled by a ground-truth rule.

Beside a pair file ``<stem>.txt`` go ``<stem>.card.json`` / ``.card.md`` (what was built and
how: counts, retrieval recall@1/5/N) and ``<stem>.candidates.csv`` (experience, rank,
similarity and label of every pair). ``config`` imports this module to register the builder.
"""

from __future__ import annotations

import json
import time
from collections.abc import Mapping
from collections.abc import Sequence as SequenceType
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from gvbench_nb.data import build_inputs, retrieval
from gvbench_nb.data.sequences import Pair, Sequence, read_pairs, summarize, write_pairs
from gvbench_nb.io_utils import atomic_write_csv, atomic_write_json, atomic_write_text
from gvbench_nb.protocol import registry

BUILDER_NAME = "retrieval"
CANDIDATE_COLUMNS = ["query", "experience", "reference", "rank", "similarity", "label"]
MULTI_EXPERIENCE_NOTE = (
    "Every reference experience competes for the same top-N slots, so the pair file lists candidates from "
    "all of them. To score a query, verify every candidate pair and keep the pair with the highest score "
    "(retrieval.best_experience; ties go to the better retrieval rank); the query's label is that pair's label."
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
    inputs: build_inputs.BuildInputs,
    descriptor: str,
    descriptor_options: Mapping[str, Any] | None = None,
    progress: bool = True,
) -> retrieval.GlobalDescriptors:
    """Rows for the chosen queries and every reference (experiences in order, stacked).

    vlad/bow fit their vocabulary on all reference experiences together (the map)."""
    method = registry.lookup("descriptor", descriptor, retrieval.GLOBAL_DESCRIPTORS, error=build_inputs.BuildError)
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


def ground_truth(inputs: build_inputs.BuildInputs) -> np.ndarray:
    """(Q, R) bool: the rule on every chosen query x every reference (experiences stacked)."""
    blocks = [
        retrieval.ground_truth_matrix(inputs.options.label_rule, inputs.rule_params, inputs.query.table, t.table)
        for t in inputs.experiences.values()
    ]
    return np.concatenate(blocks, axis=1)


def _offsets(inputs: build_inputs.BuildInputs) -> dict[str, int]:
    """Each experience's first row among the stacked references."""
    sizes = [len(t.names) for t in inputs.experiences.values()]
    return dict(zip(inputs.experiences, np.cumsum([0, *sizes[:-1]]).tolist()))


def retrieve(
    inputs: build_inputs.BuildInputs, descriptors: retrieval.GlobalDescriptors, n: int
) -> retrieval.Candidates:
    """Top-n candidates a chosen query over every experience."""
    rows = {
        folder: descriptors.reference[start : start + len(inputs.experiences[folder].names)]
        for folder, start in _offsets(inputs).items()
    }
    return retrieval.retrieve_top_n_experiences(descriptors.query, rows, n)


def stacked_indices(inputs: build_inputs.BuildInputs, candidates: retrieval.Candidates) -> np.ndarray:
    """(Q, n) candidate columns in the stacked reference order of ``ground_truth``."""
    offsets = _offsets(inputs)
    columns = np.array([offsets[e] for e in candidates.experience], dtype=np.int64) + candidates.reference
    return columns.reshape(len(inputs.query.names), -1)


def label_candidates(inputs: build_inputs.BuildInputs, candidates: retrieval.Candidates) -> np.ndarray:
    """(P,) labels of candidate pairs, by the rule applied experience by experience."""
    labels = np.zeros(len(candidates), dtype=bool)
    for folder, traversal in inputs.experiences.items():
        mine = candidates.experience == folder
        pairs = np.stack([candidates.query[mine], candidates.reference[mine]], axis=1)
        labels[mine] = retrieval.label_pairs(
            inputs.options.label_rule, inputs.rule_params, inputs.query.table, traversal.table, pairs
        )
    return labels


def candidate_frame(
    inputs: build_inputs.BuildInputs, candidates: retrieval.Candidates, labels: np.ndarray
) -> pd.DataFrame:
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
    inputs: build_inputs.BuildInputs,
    frame: pd.DataFrame,
    truth: np.ndarray,
    recall: dict[str, float],
    seconds: dict[str, float],
    files: dict[str, Path],
) -> dict[str, Any]:
    """The sequence card: how the pairs were made, and counts computed from the pairs written."""
    from gvbench_nb.methods import conf_hash

    options = inputs.options
    feature_conf = (
        local_feature_conf(options, inputs.params["profile"])
        if retrieval.GLOBAL_DESCRIPTORS[options.descriptor].inputs == "local_descriptors"
        else None
    )
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
            "shared_with_method": build_inputs.LOCAL_FEATURE_METHODS[options.local_features],
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


def build_sequence(build_params: Mapping[str, Any], progress: bool = True) -> dict[str, Any]:
    """Build the pair file of a loaded params dict (``pairs_builder: retrieval``) and
    its card; returns the card. Overwrites ``build_params['pairs']`` and the card files."""
    inputs = build_inputs.prepare_inputs(build_params)
    options = inputs.options
    started = time.perf_counter()
    descriptors = global_descriptors(
        inputs, options.descriptor, inputs.descriptor_options(options.descriptor), progress
    )
    described = time.perf_counter()
    candidates = retrieve(inputs, descriptors, options.top_n)
    labels = label_candidates(inputs, candidates)
    truth = ground_truth(inputs)
    top_n = min(options.top_n, truth.shape[1])
    ks = sorted({k for k in (1, 5, top_n) if k <= top_n})  # the card's recall@1, 5 and N
    recall = retrieval.retrieval_recall_at(ks, stacked_indices(inputs, candidates), truth)
    retrieved = time.perf_counter()
    frame = candidate_frame(inputs, candidates, labels)
    files = card_paths(build_params["pairs"])
    write_pairs(files["pairs"], zip(frame["query"], frame["reference"], frame["label"]))
    seconds = {"descriptors": described - started, "retrieval_and_labels": retrieved - described}
    card = make_card(inputs, frame, truth, recall, seconds, files)
    atomic_write_csv(files["candidates"], frame)
    atomic_write_json(files["card_json"], card)
    atomic_write_text(files["card_markdown"], card_markdown(card))
    return card


def build_retrieval_pairs(params: dict[str, Any]) -> None:
    """``config.PAIR_BUILDERS['retrieval']``: writes ``params['pairs']`` (and the card)."""
    build_sequence(params)


def check_card(pairs_path: str | Path) -> None:
    """Raise when a card's counts disagree with its pair file (e.g. the file was edited)."""
    card = json.loads(card_paths(pairs_path)["card_json"].read_text(encoding="utf-8"))
    counts = summarize(Sequence(card["sequence"] or "build", Path("."), read_pairs(pairs_path)))
    wrong = {k: (card["counts"][k], v) for k, v in counts.items() if k != "sequence" and card["counts"].get(k) != v}
    if wrong:
        raise build_inputs.BuildError(
            f"{pairs_path}: card counts differ from the pair file (card, file): {wrong}; rebuild it"
        )
