"""Loop-closure candidates as GV-Bench built them: top-N retrieval by a global descriptor
(``GLOBAL_DESCRIPTORS``, dot-product similarity), then a label rule (``LABEL_RULES``) per pair.
Frame tables map column -> one row a frame (name, frame, position (N, 2|3) m, heading deg)."""

from __future__ import annotations

from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from gvbench_nb.protocol import registry

FrameTable = Mapping[str, Any]
LocalDescriptors = Mapping[str, np.ndarray]


def frame_table(
    names: Sequence[str],
    frames: Sequence[int] | np.ndarray | None = None,
    positions: Sequence[Sequence[float]] | np.ndarray | None = None,
    headings: Sequence[float] | np.ndarray | None = None,
) -> dict[str, np.ndarray]:
    """A frame table of the columns given."""
    columns: dict[str, tuple[Any, Any]] = {"name": (names, object), "frame": (frames, np.int64)}
    columns |= {"position": (positions, np.float64), "heading": (headings, np.float64)}
    return {key: np.asarray(values, dtype) for key, (values, dtype) in columns.items() if values is not None}


def _column(table: FrameTable, column: str, rule: str) -> np.ndarray:
    if column not in table:
        raise KeyError(f"label rule {rule!r} needs the frame-table column {column!r}; got {sorted(table)}")
    return np.asarray(table[column])


def heading_difference_deg(a: np.ndarray | float, b: np.ndarray | float) -> np.ndarray:
    """Smallest absolute angle between headings in degrees, in [0, 180] (359 vs 1 -> 2)."""
    difference = np.mod(np.asarray(a, float) - np.asarray(b, float), 360.0)
    return np.minimum(difference, 360.0 - difference)


def _pose_rule(
    params: Mapping[str, Any], query: FrameTable, reference: FrameTable, qi: np.ndarray, ri: np.ndarray
) -> np.ndarray:
    """True within ``max_distance_m`` (Euclidean, metres) and ``max_heading_deg``
    (wrapped); ``max_heading_deg=None`` ignores heading. Both bounds inclusive."""
    q_pos = _column(query, "position", "pose")[qi]
    r_pos = _column(reference, "position", "pose")[ri]
    close = np.linalg.norm(q_pos - r_pos, axis=-1) <= params["max_distance_m"]
    if params.get("max_heading_deg") is None:
        return close
    q_head = _column(query, "heading", "pose")[qi]
    r_head = _column(reference, "heading", "pose")[ri]
    return close & (heading_difference_deg(q_head, r_head) <= params["max_heading_deg"])


def _frame_tolerance_rule(
    params: Mapping[str, Any], query: FrameTable, reference: FrameTable, qi: np.ndarray, ri: np.ndarray
) -> np.ndarray:
    """True when the frame indices differ by at most ``k`` (frame-aligned traversals)."""
    q_frame = _column(query, "frame", "frame_tolerance").astype(np.int64)[qi]
    r_frame = _column(reference, "frame", "frame_tolerance").astype(np.int64)[ri]
    return np.abs(q_frame - r_frame) <= int(params["k"])


def _manual_rule(
    params: Mapping[str, Any], query: FrameTable, reference: FrameTable, qi: np.ndarray, ri: np.ndarray
) -> np.ndarray:
    """True exactly for the listed ``true_pairs`` of (query name, reference name)."""
    q_row = {str(n): i for i, n in enumerate(_column(query, "name", "manual"))}
    r_names = _column(reference, "name", "manual")
    r_row = {str(n): i for i, n in enumerate(r_names)}
    # pairs as codes q * R + r; pairs naming frames outside these tables are irrelevant here
    true_codes = [
        q_row[str(q)] * len(r_names) + r_row[str(r)]
        for q, r in params["true_pairs"]
        if str(q) in q_row and str(r) in r_row
    ]
    return np.isin(np.asarray(qi, np.int64) * len(r_names) + np.asarray(ri, np.int64), np.array(true_codes, np.int64))


@dataclass(frozen=True)
class LabelRule:
    """``evaluate(params, query, reference, qi, ri)``: booleans for index arrays that broadcast."""

    default_params: Mapping[str, Any]
    evaluate: Callable[[Mapping[str, Any], FrameTable, FrameTable, np.ndarray, np.ndarray], np.ndarray]


LABEL_RULES: dict[str, LabelRule] = {
    "pose": LabelRule({"max_distance_m": 25.0, "max_heading_deg": 40.0}, _pose_rule),  # MSLS: 25 m, 40 deg
    "frame_tolerance": LabelRule({"k": 2}, _frame_tolerance_rule),  # Nordland, Gardens Point: k = 2
    "manual": LabelRule({"true_pairs": ()}, _manual_rule),
}


def rule_params(rule_name: str, params: Mapping[str, Any] | None) -> dict[str, Any]:
    """The rule's defaults overridden by ``params``; an unknown rule or parameter raises KeyError."""
    defaults = registry.lookup("label rule", rule_name, LABEL_RULES).default_params
    merged = {**defaults, **(params or {})}
    unknown = set(merged) - set(defaults)
    if unknown:
        raise KeyError(f"label rule {rule_name!r} has no parameter(s) {sorted(unknown)}; known: {sorted(defaults)}")
    return merged


def ground_truth_matrix(
    rule_name: str, params: Mapping[str, Any] | None, query_meta: FrameTable, reference_meta: FrameTable
) -> np.ndarray:
    """(Q, R) bool: every query against every reference under a named rule (``params`` override its defaults)."""
    merged = rule_params(rule_name, params)
    qi = np.arange(len(query_meta["name"]))[:, None]
    ri = np.arange(len(reference_meta["name"]))[None, :]
    truth = LABEL_RULES[rule_name].evaluate(merged, query_meta, reference_meta, qi, ri)
    return np.broadcast_to(np.asarray(truth, bool), (qi.shape[0], ri.shape[1])).copy()


def _as_float_words(descriptors: np.ndarray) -> np.ndarray:
    """float32 rows; binary (uint8) ones unpacked to 0/1 bits: squared Euclidean = Hamming."""
    descriptors = np.asarray(descriptors)
    if descriptors.dtype == np.uint8:
        return np.unpackbits(descriptors, axis=1).astype(np.float32)
    return descriptors.astype(np.float32, copy=False)


def fit_vocabulary(
    local: LocalDescriptors, num_words: int, seed: int = 0, max_descriptors: int = 100_000
) -> np.ndarray:
    """Seeded mini-batch k-means centres (num_words, D) over up to ``max_descriptors`` rows, images sorted
    by name (the mapping's order does not matter). One OpenMP thread: OpenMP's busy-waiting makes
    k-means 10x+ slower on shared, oversubscribed cores."""
    from sklearn.cluster import MiniBatchKMeans
    from threadpoolctl import threadpool_limits

    stacked = [_as_float_words(local[name]) for name in sorted(local) if len(local[name])]
    if not stacked:
        raise ValueError("no local descriptors to fit a vocabulary on")
    data = np.concatenate(stacked)
    if len(data) > max_descriptors:
        rows = np.random.default_rng(seed).choice(len(data), size=max_descriptors, replace=False)
        data = data[np.sort(rows)]
    if len(data) < num_words:
        raise ValueError(f"{len(data)} descriptors cannot make {num_words} words")
    model = MiniBatchKMeans(num_words, random_state=seed, batch_size=max(4096, 4 * num_words), n_init=1, max_iter=100)
    with threadpool_limits(limits=1, user_api="openmp"):
        model.fit(data)
    return model.cluster_centers_.astype(np.float32)


def assign_words(descriptors: np.ndarray, centres: np.ndarray, chunk: int = 8192) -> np.ndarray:
    """Nearest centre (squared Euclidean) of every descriptor row; ties -> lowest index."""
    data = _as_float_words(descriptors)
    centres = np.asarray(centres, dtype=np.float32)
    centre_norms = (centres**2).sum(1)
    words = np.empty(len(data), dtype=np.int64)
    for start in range(0, len(data), chunk):
        # |x - c|^2 = |x|^2 - 2 x.c + |c|^2; |x|^2 is constant per row
        distances = centre_norms[None, :] - 2.0 * (data[start : start + chunk] @ centres.T)
        words[start : start + chunk] = distances.argmin(1)
    return words


def _l2_rows(x: np.ndarray) -> np.ndarray:
    norms = np.linalg.norm(x, axis=-1, keepdims=True)
    return np.divide(x, norms, out=np.zeros_like(x), where=norms > 0)


def vlad_encode(descriptors: np.ndarray, centres: np.ndarray) -> np.ndarray:
    """VLAD (Jegou et al.): per word the sum of residuals x - c_k of the descriptors assigned to it, then
    signed square root, intra (per word) and global L2 normalisation (Arandjelovic & Zisserman, "All about
    VLAD"); (K * D,) float32, all zeros for an image without descriptors."""
    vlad = np.zeros(centres.shape, dtype=np.float64)
    if len(descriptors):
        data = _as_float_words(descriptors).astype(np.float64)
        words = assign_words(data, centres)
        np.add.at(vlad, words, data - centres[words])
    vlad = _l2_rows(np.sign(vlad) * np.abs(vlad) ** 0.5)  # intra-normalisation: stops bursty words dominating
    return _l2_rows(vlad.reshape(-1)).astype(np.float32)


def vlad(
    reference_local: LocalDescriptors,
    query_local: LocalDescriptors,
    num_words: int = 64,
    seed: int = 0,
    **vocabulary: Any,
) -> tuple[np.ndarray, np.ndarray]:
    """VLAD rows (reference, query), the vocabulary fitted on the references."""
    centres = fit_vocabulary(reference_local, num_words, seed, **vocabulary)
    encode = lambda descriptors: vlad_encode(descriptors, centres)
    return _encoded_rows(encode, reference_local, centres.size), _encoded_rows(encode, query_local, centres.size)


def bow(
    reference_local: LocalDescriptors,
    query_local: LocalDescriptors,
    num_words: int = 1000,
    seed: int = 0,
    **vocabulary: Any,
) -> tuple[np.ndarray, np.ndarray]:
    """Bag of visual words, tf-idf weighted and L2-normalised (DBoW2 scores ORB-SLAM's candidates so);
    idf = log(N / n_w) over the N references (log N for unseen words)."""
    centres = fit_vocabulary(reference_local, num_words, seed, **vocabulary)
    counts = np.zeros(num_words, dtype=np.int64)
    for descriptors in reference_local.values():
        if len(descriptors):
            counts[np.unique(assign_words(descriptors, centres))] += 1
    idf = np.log(len(reference_local) / np.maximum(counts, 1)).astype(np.float32)

    def encode(descriptors: np.ndarray) -> np.ndarray:
        if not len(descriptors):
            return np.zeros(num_words, dtype=np.float32)
        words = np.bincount(assign_words(descriptors, centres), minlength=num_words)
        return _l2_rows(words / words.sum() * idf).astype(np.float32)

    return _encoded_rows(encode, reference_local, num_words), _encoded_rows(encode, query_local, num_words)


def _encoded_rows(encode: Callable[[np.ndarray], np.ndarray], local: LocalDescriptors, dim: int) -> np.ndarray:
    """(N, dim) float32: one encoded row an image, in the mapping's order ((0, dim) for no images)."""
    return np.array([encode(d) for d in local.values()], np.float32).reshape(len(local), dim)


def netvlad(
    reference_images: Mapping[str, str], query_images: Mapping[str, str], device: str = "cpu"
) -> tuple[np.ndarray, np.ndarray]:
    """NetVLAD (Pitts30K) rows (reference, query) over image files ``{name: path}``; needs the .mat weights."""
    from gvbench_nb.data.netvlad import describe_images, load_netvlad

    model = load_netvlad(device)
    return describe_images(model, reference_images.values()), describe_images(model, query_images.values())


# name -> compute(reference_inputs, query_inputs, **options): (reference rows, query rows)
GLOBAL_DESCRIPTORS: dict[str, Callable[..., tuple[np.ndarray, np.ndarray]]] = {
    "netvlad": netvlad,  # GV-Bench's retrieval
    "vlad": vlad,
    "bow": bow,  # tf-idf, DBoW-like
}
IMAGE_DESCRIPTORS = ("netvlad",)  # read {name: image path}; the others aggregate {name: local descriptors}


def retrieve_top_n(
    query_descriptors: np.ndarray, reference_descriptors: np.ndarray, n: int, chunk: int = 1024
) -> tuple[np.ndarray, np.ndarray]:
    """Top-min(n, R) reference rows and similarities per query by dot product, best first (ties: lower row)."""
    query = np.asarray(query_descriptors, dtype=np.float32)
    reference = np.asarray(reference_descriptors, dtype=np.float32)
    if query.ndim != 2 or reference.ndim != 2 or query.shape[1] != reference.shape[1]:
        raise ValueError(f"descriptor shapes do not match: {query.shape} vs {reference.shape}")
    if n < 1:
        raise ValueError(f"n must be >= 1, got {n}")
    n = min(n, reference.shape[0])
    indices = np.empty((len(query), n), dtype=np.int64)
    similarities = np.empty((len(query), n), dtype=np.float32)
    for start in range(0, len(query), chunk):  # chunks bound the (chunk, R) similarity block
        block = query[start : start + chunk] @ reference.T
        order = np.argsort(-block, axis=1, kind="stable")[:, :n]
        indices[start : start + chunk] = order
        similarities[start : start + chunk] = np.take_along_axis(block, order, axis=1)
    return indices, similarities


def retrieval_recall_at(ks: Iterable[int], ranked_indices: np.ndarray, ground_truth: np.ndarray) -> dict[str, float]:
    """Recall@k: the fraction of queries with a true reference among their top k. Queries with
    no true reference at all are excluded (no retrieval can succeed; ``queries_excluded``);
    k > n raises (it would silently be recall@n)."""
    ranked = np.asarray(ranked_indices, dtype=np.int64)
    truth = np.asarray(ground_truth, dtype=bool)
    if ranked.shape[0] != truth.shape[0]:
        raise ValueError(f"{ranked.shape[0]} ranked queries vs {truth.shape[0]} ground-truth rows")
    hits = np.take_along_axis(truth, ranked, axis=1)  # (Q, n): is the ranked reference true?
    answerable = truth.any(axis=1)
    result: dict[str, float] = {}
    for k in ks:
        if not 1 <= k <= ranked.shape[1]:
            raise ValueError(f"recall@{k} needs 1 <= k <= {ranked.shape[1]} ranked references")
        found = hits[answerable, :k].any(axis=1)
        result[f"recall@{k}"] = float(found.mean()) if found.size else float("nan")
    result["queries_evaluated"] = int(answerable.sum())
    result["queries_excluded"] = int((~answerable).sum())
    return result


def choose_queries(num_frames: int, count: int | None = None, seed: int = 0) -> np.ndarray:
    """Query rows: all frames (``count=None``) or a seeded random subset, sorted."""
    if count is None or count >= num_frames:
        return np.arange(num_frames)
    return np.sort(np.random.default_rng(seed).choice(num_frames, size=count, replace=False))
