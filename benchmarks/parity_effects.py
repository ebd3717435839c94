"""What each remaining difference from the reference code moves: AP and MR of a method scored
both ways on the same pairs and the same cached features, the package's reading and the
reference's reading, with how many matches and inliers changed and on how many pairs.

Rows (each one difference; the reference is the paper's hloc chain or the GV-Bench
repository's code, as the row says):

- ``score-float16`` (paper profile, SuperGlue / LightGlue): the reference (the paper's hloc)
  stores ``matching_scores0`` as float16, so the ``> 0.5`` score filter sees the rounded
  scores; ours filters the float32 scores.
- ``descriptors-as-stored`` (paper profile, NN and LightGlue): the reference (the paper's
  hloc) matches the stored float16 descriptors as they are (``.float()``); our nearest
  neighbour L2-normalises them again. Our LightGlue reads them as stored, as hloc does.
- ``lightglue-input-size`` (repository profile, LightGlue): the reference (the repository's
  cvg ``match_pair``) gives LightGlue keypoints in the 512x288 input's pixels and that size;
  ours gives the original pixels and the original size.
- ``float-images`` (repository profile, learned extractors): the reference (the
  repository's image chain) hands the model the float image; ours rounds it to 8 bits.
- ``cvg-lightglue`` (paper profile, LightGlue): cvg's ``lightglue`` package (the paper's
  hloc runs it) against kornia's LightGlue (ours) on the same cached features, with the
  same conf and original image sizes. cvg's file is loaded from the opt-in environment
  (``make setup-imm``: vismatch's ``third_party/LightGlue/lightglue/lightglue.py``) or
  ``--cvg-lightglue``; its weights are the package's own LightGlue checkpoints.

Features are extracted once per (profile, extractor) into the package's content-keyed
cache and read by both readings; ``float-images`` extracts its reference reading into a
cache of its own (``<cache-dir>/float-images``). Pairs: every pair of the params file, or
``--query-step N``: the pairs of every Nth query in the order of the pair list (a
deterministic subset, labelled as such in the output).

    python benchmarks/parity_effects.py params/gardens_point.yaml --rows score-float16,cvg-lightglue \\
        --query-step 10

Writes ``<output-dir>/<sequence>/parity_effects.csv`` (one line a row, method and reading;
the reference line carries the changes from ours and a paired bootstrap interval of the AP
and MR change over query resamples) and prints it.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import glob
import importlib.util
import sys
import types
from collections.abc import Callable, Iterator
from collections.abc import Sequence as SequenceType
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pandas as pd
import torch
from tqdm import tqdm

from gvbench_nb import methods
from gvbench_nb.data.sequences import Sequence
from gvbench_nb.evaluation import bootstrap as resampling
from gvbench_nb.protocol import images, metrics, weights
from gvbench_nb.protocol.ransac import to_verifier_frame, verify_matches
from gvbench_nb.protocol.recipes import conf_hash
from gvbench_nb.runner import concurrency, config, image_features, pair_matching, sequence_build

Features = dict[str, np.ndarray]
Matches = tuple[np.ndarray, np.ndarray]
Matcher = Callable[[Features, Features], Matches]

REPO_ROOT = Path(__file__).resolve().parents[1]
CVG_LIGHTGLUE_GLOB = ".venv-imm/lib/python*/site-packages/vismatch/third_party/LightGlue/lightglue/lightglue.py"


# ------------------------------------------------------------------- the readings --
def float16_scores(scores: np.ndarray) -> np.ndarray:
    """Match scores as hloc's match file stores them (float16), read back as float32."""
    return np.asarray(scores, dtype=np.float32).astype(np.float16).astype(np.float32)


@contextlib.contextmanager
def descriptors_as_stored() -> Iterator[None]:
    """Our nearest-neighbour matcher without its re-normalisation: the product of the stored
    descriptors as they are, as hloc's ``nearest_neighbor`` takes it. Single-threaded use only."""
    normalize = torch.nn.functional.normalize

    def as_is(tensor: torch.Tensor, *args: Any, **kwargs: Any) -> torch.Tensor:
        return tensor

    torch.nn.functional.normalize = as_is  # type: ignore[assignment]
    try:
        yield
    finally:
        torch.nn.functional.normalize = normalize


def in_input_frame(features: Features, size: SequenceType[int]) -> Features:
    """One image's features as cvg's ``match_pair`` hands them to LightGlue in the repository's
    code: keypoints in the pixels of the ``size`` (width, height) input, and that size."""
    frame = {"coordinates": "resize_to", "resize_to": list(size)}
    keypoints = to_verifier_frame(features["keypoints"], features["image_size"], frame)
    return {**features, "keypoints": keypoints.astype(np.float32), "image_size": np.array(list(size), np.int64)}


def load_float_as_repository(path: str | Path, conf: dict[str, Any]) -> tuple[np.ndarray, np.ndarray]:
    """``images.load_for_extraction`` for a repository-profile learned extractor, left in float
    where ours rounds to 8 bits: RGB as float, torchvision's antialiased bilinear resize to
    ``resize_to``, grey where the conf says so, the model's own input resize, and no rounding
    (values in 0..255; the repository's are the same divided by 255, which the extractors undo)."""
    if conf.get("interpolation") != "bilinear_antialias" or not conf.get("resize_to"):
        raise ValueError(f"extractor conf {conf.get('name', '?')!r} is not a repository-profile conf")
    if conf.get("normalize_minmax"):
        raise ValueError("the OpenCV matchers' chain is the repository's 8-bit one; nothing to compare")
    rgb = images.read_image(path, grayscale=False).astype(np.float32)
    height, width = rgb.shape[:2]
    image = images.resize_bilinear_antialias(rgb, tuple(int(v) for v in conf["resize_to"]))
    if conf.get("grayscale", False):
        image = cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)
    long_side = conf.get("model_input_long_side")
    if long_side:
        scale = long_side / max(image.shape[:2])
        image = images.resize_bilinear_antialias(image, (int(image.shape[1] * scale), int(image.shape[0] * scale)))
    multiple_of = conf.get("multiple_of")
    if multiple_of:
        h, w = image.shape[:2]
        image = images.resize_bilinear_antialias(
            image, (w // multiple_of * multiple_of, h // multiple_of * multiple_of)
        )
    size = image.shape[1::-1]
    return image.astype(np.float32), (np.array([width, height]) / np.array(size)).astype(np.float32)


@contextlib.contextmanager
def float_images() -> Iterator[None]:
    """The package's extraction with the float image chain in place of the 8-bit one."""
    if not hasattr(image_features, "load_for_extraction"):
        raise RuntimeError("image_features no longer reads images through load_for_extraction; update this script")
    saved = image_features.load_for_extraction
    image_features.load_for_extraction = load_float_as_repository  # type: ignore[assignment]
    try:
        yield
    finally:
        image_features.load_for_extraction = saved  # type: ignore[assignment]


def cvg_lightglue_file(given: str | None) -> Path:
    if given:
        return Path(given)
    spec = importlib.util.find_spec("vismatch")
    if spec is not None and spec.submodule_search_locations:
        found = Path(next(iter(spec.submodule_search_locations))) / "third_party/LightGlue/lightglue/lightglue.py"
        if found.is_file():
            return found
    matches = sorted(glob.glob(str(REPO_ROOT / CVG_LIGHTGLUE_GLOB)))
    if not matches:
        raise FileNotFoundError(f"cvg's lightglue.py is not in {CVG_LIGHTGLUE_GLOB}: run make setup-imm or pass it")
    return Path(matches[0])


def load_cvg_lightglue(path: Path) -> type:
    """cvg's LightGlue class from its file (its package's __init__, which imports its
    extractors, is not run)."""
    if "cvg_lightglue" not in sys.modules:
        package = types.ModuleType("cvg_lightglue")
        package.__path__ = [str(path.parent)]
        sys.modules["cvg_lightglue"] = package
    name = "cvg_lightglue.lightglue"
    if name not in sys.modules:
        spec = importlib.util.spec_from_file_location(name, path)
        assert spec is not None and spec.loader is not None
        module = importlib.util.module_from_spec(spec)
        sys.modules[name] = module
        spec.loader.exec_module(module)
    return sys.modules[name].LightGlue


class CvgLightGlue:
    """cvg's LightGlue called as hloc's wrapper calls it: keypoints, descriptors and the
    original ``image_size`` of each side; weights from the package's checkpoint of the same file."""

    def __init__(self, matcher_conf: dict[str, Any], path: Path):
        features = matcher_conf["features"]
        checkpoint = weights.checkpoint_path(f"lightglue_{features}")
        options = {k: matcher_conf[k] for k in ("depth_confidence", "width_confidence", "filter_threshold")}
        download = torch.hub.load_state_dict_from_url
        torch.hub.load_state_dict_from_url = lambda *a, **k: weights.load_checkpoint(checkpoint)  # type: ignore[assignment]
        try:
            self.model = load_cvg_lightglue(path)(features, **options).eval()
        finally:
            torch.hub.load_state_dict_from_url = download  # type: ignore[assignment]

    @torch.inference_mode()
    def __call__(self, features0: Features, features1: Features) -> Matches:
        if len(features0["keypoints"]) == 0 or len(features1["keypoints"]) == 0:
            return np.zeros((0, 2), np.int64), np.zeros((0,), np.float32)
        sides = [
            {k: torch.from_numpy(np.asarray(f[k])).float()[None] for k in ("keypoints", "descriptors", "image_size")}
            for f in (features0, features1)
        ]
        output = self.model({"image0": sides[0], "image1": sides[1]})
        return output["matches"][0].numpy().astype(np.int64), output["scores"][0].numpy().astype(np.float32)


# ----------------------------------------------------------------------- the rows --
@dataclass
class Row:
    profile: str
    methods: list[str]
    reference: str  # whose code the reference reading is
    needs: str  # "lightglue", "nn" or "learned"
    what: str
    notes: dict[str, str] = field(default_factory=dict)


ROWS: dict[str, Row] = {
    "score-float16": Row(
        "paper", ["aliked-lg"], "paper", "lightglue", "scores at the > 0.5 filter: float16 vs float32"
    ),
    "descriptors-as-stored": Row(
        "paper",
        ["aliked-nn", "xfeat-nn", "disk-nn", "aliked-lg"],
        "paper",
        "nn_or_lightglue",
        "descriptors at match time: as stored vs L2-normalised again",
    ),
    "lightglue-input-size": Row(
        "repository", ["aliked-lg"], "repository", "lightglue", "LightGlue keypoints: 512x288 input frame vs original"
    ),
    "float-images": Row(
        "repository", ["xfeat-nn", "aliked-nn"], "repository", "learned", "model input: float vs rounded to 8 bits"
    ),
    "cvg-lightglue": Row("paper", ["aliked-lg"], "paper", "cvg_lightglue", "LightGlue: cvg's package vs kornia's"),
}


def applies(row: str, conf: dict[str, Any]) -> str | None:
    """Why ``row`` does not apply to a resolved method, or None when it does."""
    matcher, extractor = conf["matcher"], conf["extractor"]
    kind = ROWS[row].needs
    if extractor is None:
        return "no stored features"
    if kind == "lightglue" and matcher["type"] != "kornia_lightglue":
        return "not a LightGlue method"
    if kind == "cvg_lightglue" and (
        matcher["type"] != "kornia_lightglue" or matcher.get("features") not in ("disk", "aliked")
    ):
        return "not a LightGlue method cvg's package has weights for here (disk, aliked)"
    if kind == "nn_or_lightglue" and not (
        matcher["type"] == "kornia_lightglue" or (matcher["type"] == "nn" and matcher.get("metric", "l2") == "l2")
    ):
        return "not an L2 nearest-neighbour or LightGlue method"
    if kind == "learned" and extractor["type"] in ("colmap_sift", "opencv_sift", "opencv_orb"):
        return "an OpenCV extractor: its 8-bit chain is the repository's"
    return None


# ------------------------------------------------------------------ the scoring --
def query_subset(sequence: Sequence, step: int) -> Sequence:
    """The pairs of every ``step``-th query, queries in the order the pair list first names them."""
    if step == 1:
        return sequence
    order = list(dict.fromkeys(pair.query for pair in sequence.pairs))
    kept = set(order[::step])
    return dataclasses.replace(sequence, pairs=[p for p in sequence.pairs if p.query in kept])


def read_features(sequence: Sequence, extractor_conf: dict[str, Any], cache_dir: Path) -> Callable[[str], Features]:
    store = image_features.feature_store(cache_dir, extractor_conf)
    store.refresh()
    cache = pair_matching.FeatureCache(lambda name: store.read(image_features.image_key(sequence.image_root, name)))
    return cache.get


def score_pairs(
    sequence: Sequence,
    conf: dict[str, Any],
    features: Callable[[str], Features],
    match: Matcher,
    seed: int,
    transform_scores: Callable[[np.ndarray], np.ndarray] | None = None,
    matches_of: dict[int, Matches] | None = None,
    desc: str = "match",
) -> tuple[pd.DataFrame, list[tuple[np.ndarray, np.ndarray]]]:
    """Each pair matched by ``match`` (or taken from ``matches_of``), its scores passed through
    ``transform_scores``, then verified as the package verifies. Returns the pairs table
    (query, reference, label, num_matches, num_matches_filtered, num_inliers, score) and each
    pair's filtered matches (those that entered the fit) as (x0, y0, x1, y1) rows in original
    pixels rounded to whole pixels, so that readings with different keypoints compare too."""
    rows, kept = [], []
    verifier = conf["verifier"]
    for index, pair in enumerate(tqdm(sequence.pairs, desc=desc, unit="pair", leave=False)):
        f0, f1 = features(pair.query), features(pair.reference)
        pair_matches, scores = matches_of[index] if matches_of is not None else match(f0, f1)
        if transform_scores is not None:
            scores = transform_scores(scores)
        verified = verify_matches(
            f0["keypoints"],
            f1["keypoints"],
            pair_matches,
            scores,
            verifier,
            seed=pair_matching.pair_seed(seed, pair.query, pair.reference),
            image_sizes=(f0.get("image_size"), f1.get("image_size")),
        )
        threshold = verifier.get("min_match_score")
        keep = np.ones(len(pair_matches), bool) if threshold is None else np.asarray(scores) > threshold
        positions = np.round(np.hstack([f0["keypoints"][pair_matches[:, 0]], f1["keypoints"][pair_matches[:, 1]]]))
        kept.append((positions, keep))
        rows.append(
            {
                "query": pair.query,
                "reference": pair.reference,
                "label": int(pair.label),
                "num_matches": verified["num_matches"],
                "num_matches_filtered": verified["num_matches_filtered"],
                "num_inliers": verified["num_inliers"],
                "score": verified["num_inliers"],
            }
        )
    return pd.DataFrame(rows), kept


def changes(ours: tuple[pd.DataFrame, list], theirs: tuple[pd.DataFrame, list]) -> dict[str, int]:
    """Matches added or removed, by their keypoints' positions, before the score filter (raw)
    and after it, with the pairs touched; inliers added or removed, by count, and the pairs touched."""

    def changed(a: np.ndarray, b: np.ndarray) -> int:
        return len({tuple(m) for m in a.tolist()} ^ {tuple(m) for m in b.tolist()})

    raw = [changed(a, b) for (a, _), (b, _) in zip(ours[1], theirs[1])]
    filtered = [changed(a[keep_a], b[keep_b]) for (a, keep_a), (b, keep_b) in zip(ours[1], theirs[1])]
    inlier_change = (theirs[0]["num_inliers"] - ours[0]["num_inliers"]).abs()
    return {
        "raw_matches_changed": int(sum(raw)),
        "pairs_raw_matches_changed": int(sum(c > 0 for c in raw)),
        "matches_changed": int(sum(filtered)),
        "pairs_matches_changed": int(sum(c > 0 for c in filtered)),
        "inliers_changed": int(inlier_change.sum()),
        "pairs_inliers_changed": int((inlier_change > 0).sum()),
    }


def summary(table: pd.DataFrame) -> dict[str, Any]:
    labels, scores = table["label"].to_numpy(), table["score"].to_numpy(dtype=float)
    return {
        "n_pairs": len(table),
        "n_positives": int(labels.sum()),
        "mean_matches": round(float(table["num_matches_filtered"].mean()), 2),
        "mean_inliers": round(float(table["num_inliers"].mean()), 2),
        "ap": metrics.average_precision(labels, scores),
        "max_recall": metrics.max_recall_at_full_precision(labels, scores),
    }


def change_interval(ours: pd.DataFrame, theirs: pd.DataFrame, resamples: int, seed: int) -> dict[str, float]:
    """95 % percentile interval of reference - ours (AP and MR) over paired query resamples."""
    if resamples == 0:
        return {}
    boot = resampling.bootstrap({"ours": ours, "reference": theirs}, n_resamples=resamples, seed=seed)
    out = {}
    for metric in ("ap", "max_recall"):
        difference = (boot.samples[metric]["reference"] - boot.samples[metric]["ours"]).dropna().to_numpy()
        low, high = np.percentile(difference, [2.5, 97.5]) if len(difference) else (np.nan, np.nan)
        out[f"{metric}_change_low"], out[f"{metric}_change_high"] = float(low), float(high)
    return out


@dataclass
class Context:
    sequence: Sequence
    cache_dir: Path
    seed: int
    cvg_path: str | None
    device: str = "cpu"
    _matchers: dict[str, Any] = field(default_factory=dict)
    _ours: dict[str, dict[int, Matches]] = field(default_factory=dict)

    def extract(self, conf: dict[str, Any], cache_dir: Path | None = None) -> Callable[[str], Features]:
        cache_dir = cache_dir or self.cache_dir
        image_features.extract_features(self.sequence, conf["extractor"], cache_dir, device=self.device, jobs=1)
        return read_features(self.sequence, conf["extractor"], cache_dir)

    def matcher(self, conf: dict[str, Any]) -> Any:
        from gvbench_nb.protocol.matching import build_matcher

        key = conf_hash(conf["matcher"])
        if key not in self._matchers:
            self._matchers[key] = build_matcher(conf["matcher"], torch.device(self.device))
        return self._matchers[key]

    def ours(self, conf: dict[str, Any], features: Callable[[str], Features], call: Matcher) -> dict[int, Matches]:
        """Our matches of every pair under one (extractor, matcher) conf, computed once a run."""
        key = conf_hash({k: conf[k] for k in ("extractor", "matcher")})
        if key not in self._ours:
            self._ours[key] = match_all(self.sequence, features, call, f"{conf['method']} ours")
        return self._ours[key]


def match_all(sequence: Sequence, features: Callable[[str], Features], call: Matcher, desc: str) -> dict[int, Matches]:
    pairs = tqdm(sequence.pairs, desc=desc, unit="pair", leave=False)
    return {i: call(features(p.query), features(p.reference)) for i, p in enumerate(pairs)}


def matcher_call(matcher: Any) -> Matcher:
    """Our matcher as the package runs it: LightGlue through its per-image prepared path when
    it has one (the same matches as the per-pair call), else the per-pair call."""
    if not getattr(matcher, "can_prepare", False):
        return matcher
    states: dict[int, Any] = {}

    def match(f0: Features, f1: Features) -> Matches:
        prepared = []
        for f in (f0, f1):
            if id(f) not in states:
                states[id(f)] = (f, matcher.prepare(f))
            prepared.append(states[id(f)][1])
        return matcher.match_prepared(*prepared)

    return match


def run_row(row: str, method: str, ctx: Context) -> tuple[dict[str, Any], tuple, tuple, str]:
    """(row conf, ours, reference, note) for one row and method."""
    spec = ROWS[row]
    conf = methods.resolve_method(method, spec.profile)
    note = ""
    features = ctx.extract(conf)
    matcher = ctx.matcher(conf)
    ours_call = matcher_call(matcher)
    seq, seed = ctx.sequence, ctx.seed
    ours = score_pairs(seq, conf, features, ours_call, seed, matches_of=ctx.ours(conf, features, ours_call))
    if row == "score-float16":
        matched = ctx.ours(conf, features, ours_call)
        theirs = score_pairs(seq, conf, features, ours_call, seed, float16_scores, matched, "verify reference")
    elif row == "descriptors-as-stored":
        if conf["matcher"]["type"] == "kornia_lightglue":
            theirs = ours
            note = "our LightGlue reads the stored descriptors as they are: both readings are one computation"
        else:
            with descriptors_as_stored():
                theirs = score_pairs(seq, conf, features, ours_call, seed, desc=f"{method} reference")
    elif row == "lightglue-input-size":
        framed: dict[str, Features] = {}

        def in_frame(name: str) -> Features:
            if name not in framed:
                framed[name] = in_input_frame(features(name), conf["verifier"]["resize_to"])
            return framed[name]

        # The matcher sees the input-frame features; verification reads the stored ones.
        matched = match_all(seq, in_frame, matcher_call(matcher), f"{method} reference")
        theirs = score_pairs(seq, conf, features, ours_call, seed, matches_of=matched, desc="verify reference")
    elif row == "float-images":
        with float_images():
            float_features = ctx.extract(conf, ctx.cache_dir / "float-images")
        theirs = score_pairs(seq, conf, float_features, matcher_call(matcher), seed, desc=f"{method} reference")
    elif row == "cvg-lightglue":
        cvg = CvgLightGlue(conf["matcher"], cvg_lightglue_file(ctx.cvg_path))
        theirs = score_pairs(seq, conf, features, cvg, seed, desc=f"{method} cvg")
        note = f"cvg's file: {cvg_lightglue_file(ctx.cvg_path)}"
    else:
        raise KeyError(row)
    return conf, ours, theirs, note


def write_csv(lines: list[dict[str, Any]], path: Path) -> pd.DataFrame:
    frame = pd.DataFrame(lines).convert_dtypes()
    for column in frame.columns:
        if frame[column].dtype.kind == "f" or str(frame[column].dtype).startswith("Float"):
            frame[column] = frame[column].round(4)
    path.parent.mkdir(parents=True, exist_ok=True)
    frame.to_csv(path, index=False)
    return frame


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("params", help="params YAML, e.g. params/gardens_point.yaml")
    parser.add_argument("--rows", default=",".join(ROWS), help=f"comma-separated, of {', '.join(ROWS)} (default all)")
    parser.add_argument("--methods", default=None, help="comma-separated methods for every row (default: each row's)")
    parser.add_argument("--query-step", type=int, default=1, help="the pairs of every Nth query only (default 1: all)")
    parser.add_argument("--output-dir", default="outputs/parity_effects", help="a folder a sequence under it")
    parser.add_argument("--output-name", default="parity_effects.csv", help="the CSV's file name")
    parser.add_argument("--cache-dir", default=None, help="feature cache (default: <output-dir>/cache)")
    parser.add_argument("--resamples", type=int, default=1000, help="query resamples of the change interval (0: none)")
    parser.add_argument("--threads", type=int, default=None, help="torch and OpenCV threads (default: every core)")
    parser.add_argument("--cvg-lightglue", default=None, help="cvg's lightglue.py (default: the opt-in environment's)")
    args = parser.parse_args(argv)
    rows = [r for r in args.rows.split(",") if r]
    unknown = [r for r in rows if r not in ROWS]
    if unknown:
        parser.error(f"unknown row {unknown[0]!r}; choose from {', '.join(ROWS)}")
    if args.query_step < 1 or args.resamples < 0:
        parser.error("--query-step must be at least 1 and --resamples at least 0")
    concurrency.configure_threads(args.threads)
    params = config.load_params(args.params, profile="paper")
    full = sequence_build.prepare_sequence(params)
    sequence = query_subset(full, args.query_step)
    n_queries = len(dict.fromkeys(p.query for p in sequence.pairs))
    pairs_label = (
        f"all {len(full.pairs)} pairs"
        if args.query_step == 1
        else f"subset: every {args.query_step}th query of the pair list, {n_queries} queries, {len(sequence.pairs)} pairs"
    )
    out = Path(args.output_dir) / params["sequence"]
    cache_dir = Path(args.cache_dir) if args.cache_dir else Path(args.output_dir) / "cache"
    ctx = Context(sequence, cache_dir, int(params.get("seed", 0)), args.cvg_lightglue)
    lines: list[dict[str, Any]] = []
    for row in rows:
        spec = ROWS[row]
        for method in methods.expand_methods(args.methods) if args.methods else spec.methods:
            base = {"row": row, "profile": spec.profile, "method": method, "pairs": pairs_label}
            reason = applies(row, methods.resolve_method(method, spec.profile))
            if reason is None and not all(
                weights.is_present(c) for c in methods.required_checkpoints(method, spec.profile)
            ):
                reason = "weights missing"
            if reason:
                lines.append({**base, "reading": "", "not_run": reason})
                continue
            _, ours, theirs, note = run_row(row, method, ctx)
            mine, reference = summary(ours[0]), summary(theirs[0])
            lines.append({**base, "reading": "ours", **mine, "note": spec.what})
            lines.append(
                {
                    **base,
                    "reading": f"reference ({spec.reference}'s)",
                    **reference,
                    "ap_change": reference["ap"] - mine["ap"],
                    "max_recall_change": reference["max_recall"] - mine["max_recall"],
                    **change_interval(ours[0], theirs[0], args.resamples, ctx.seed),
                    **changes(ours, theirs),
                    "note": note or spec.what,
                }
            )
            print(pd.DataFrame(lines[-2:]).drop(columns=["pairs", "note"]).round(4).to_string(index=False), flush=True)
            write_csv(lines, out / args.output_name)  # after each method: an interrupted run keeps its rows
    frame = write_csv(lines, out / args.output_name)
    print(
        frame.drop(columns=["pairs", "note"], errors="ignore")
        .astype(object)
        .where(frame.notna(), "")
        .to_string(index=False)
    )
    print(f"pairs: {pairs_label}")
    print(out / args.output_name)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
