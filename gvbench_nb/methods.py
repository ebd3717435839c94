"""The method registry: a method is an extractor conf + a matcher conf, plain dicts.

Adding a method is one entry in ``METHODS``: its extractor and matcher are conf names from
``EXTRACTORS`` / ``MATCHERS`` or conf dicts written in the entry; a new model is one file in
``features/`` or ``matching/`` whose class the conf's ``type`` names (``docs/extending.md``).
Confs follow the paper's protocol (``docs/protocol.md``); the ``repository`` profile is the GV-Bench repository's current protocol
(fixed 512x288 images, 2048 keypoints) and is recorded in every output it produces.
"""

from __future__ import annotations

import copy
import hashlib
import json
import math
from typing import Any

from gvbench_nb import imm
from gvbench_nb.protocol import registry, weights

# store_float16: the cache keeps float arrays as float16, as hloc stores them (as_half)
# and matches them from there; it is part of the conf hash, so a profile can turn it off.
EXTRACTORS: dict[str, dict[str, Any]] = {
    # hloc's `sift` conf: its `dog` extractor, COLMAP's SIFT through pycolmap.
    "sift": {
        "type": "sift",
        "grayscale": True,
        "resize_max": 1600,
        "resize_force": False,
        "max_keypoints": 8192,
        "first_octave": 0,
        "peak_threshold": 0.01,
        "root_sift": True,
        "store_float16": True,
        "checkpoints": [],
    },
    # OpenCV's SIFT, not the paper's: kept for comparison under its own name.
    "sift-opencv": {
        "type": "opencv_sift",
        "grayscale": True,
        "resize_max": 1600,
        "resize_force": False,
        "max_keypoints": 8192,
        "peak_threshold": 0.01,
        "root_sift": True,
        "store_float16": True,
        "checkpoints": [],
    },
    "orb": {
        "type": "orb",
        "grayscale": True,
        "resize_max": 1600,
        "resize_force": False,
        "max_keypoints": 2000,
        "scale_factor": 1.2,
        "levels": 8,
        "fast_threshold": 20,
        "store_float16": True,
        "checkpoints": [],
    },
    "disk": {
        "type": "disk",
        "grayscale": False,
        "resize_max": 1600,
        "resize_force": False,
        "weights": "depth",
        "max_keypoints": 5000,
        "nms_window": 5,
        "detection_threshold": 0.0,
        "store_float16": True,
        "checkpoints": ["disk_depth"],
    },
    "superpoint": {
        "type": "superpoint",
        "grayscale": True,
        "resize_max": 1600,
        "resize_force": True,
        "nms_radius": 3,
        "keypoint_threshold": 0.005,
        "max_keypoints": 4096,
        "remove_borders": 4,
        "store_float16": True,
        "checkpoints": ["superpoint_v1"],
    },
    "aliked": {
        "type": "aliked",
        "grayscale": False,
        "resize_max": 1024,
        "resize_force": False,
        "model_name": "aliked-n16",
        "max_keypoints": 4096,
        "detection_threshold": 0.2,
        "nms_radius": 2,
        "store_float16": True,
        "checkpoints": ["aliked_n16"],
    },
    "xfeat": {
        "type": "xfeat",
        "grayscale": False,
        "resize_max": 1024,
        "resize_force": False,
        "max_keypoints": 4096,
        "detection_threshold": 0.05,
        "store_float16": True,
        "checkpoints": ["xfeat"],
    },
}

MATCHERS: dict[str, dict[str, Any]] = {
    "nn-ratio": {"type": "nn", "mutual": True, "ratio_threshold": 0.8, "distance_threshold": None, "checkpoints": []},
    "nn-distance": {
        "type": "nn",
        "mutual": True,
        "ratio_threshold": None,
        "distance_threshold": 0.7,
        "checkpoints": [],
    },
    "nn-mutual": {"type": "nn", "mutual": True, "ratio_threshold": None, "distance_threshold": None, "checkpoints": []},
    "nn-hamming": {"type": "nn", "metric": "hamming", "mutual": True, "ratio_threshold": 0.8, "checkpoints": []},
    "lightglue-disk": {
        "type": "lightglue",
        "features": "disk",
        "depth_confidence": 0.95,
        "width_confidence": 0.99,
        "filter_threshold": 0.1,
        "checkpoints": ["lightglue_disk"],
    },
    "lightglue-superpoint": {
        "type": "lightglue",
        "features": "superpoint",
        "depth_confidence": 0.95,
        "width_confidence": 0.99,
        "filter_threshold": 0.1,
        "checkpoints": ["lightglue_superpoint"],
    },
    "lightglue-aliked": {
        "type": "lightglue",
        "features": "aliked",
        "depth_confidence": 0.95,
        "width_confidence": 0.99,
        "filter_threshold": 0.1,
        "checkpoints": ["lightglue_aliked"],
    },
    # LighterGlue's own conf (kornia's 'xfeat' entry) sets its confidences; we keep them.
    "lighterglue-xfeat": {"type": "lightglue", "features": "xfeat", "checkpoints": ["lighterglue_xfeat"]},
    # Dense: matches an image pair directly; its image preparation lives in the matcher conf.
    # multiple_of_resize: match_dense's ImagePairDataset shrinks (INTER_AREA), then floors each
    # side to the multiple in a second, bilinear resize.
    # merge_*: hloc's match_dense conf `loftr` (1-px cells, 1 px max error) with its default
    # cap of 8192 keypoints an image (matchers.merge_dense_matches).
    "loftr-outdoor": {
        "type": "loftr",
        "dense": True,
        "weights": "outdoor",
        "grayscale": True,
        "resize_max": 1024,
        "resize_force": False,
        "multiple_of": 8,
        "multiple_of_resize": "bilinear",
        "coarse_threshold": 0.2,
        "merge_cell_size": 1,
        "merge_max_error": 1,
        "merge_max_keypoints": 8192,
        "checkpoints": ["loftr_outdoor"],
    },
    "superglue-outdoor": {
        "type": "superglue",
        "weights": "outdoor",
        "sinkhorn_iterations": 50,
        "match_threshold": 0.2,
        "checkpoints": ["superglue_outdoor"],
    },
}

METHODS: dict[str, dict[str, Any]] = {
    "sift-nn": {"paper_name": "SIFT+NN", "extractor": "sift", "matcher": "nn-ratio", "in_paper": True},
    "sp-nn": {"paper_name": "SP+NN", "extractor": "superpoint", "matcher": "nn-distance", "in_paper": True},
    "sp-sg": {"paper_name": "SP+SG", "extractor": "superpoint", "matcher": "superglue-outdoor", "in_paper": True},
    "disk-nn": {"paper_name": "DISK+NN", "extractor": "disk", "matcher": "nn-ratio", "in_paper": True},
    "disk-lg": {"paper_name": "DISK+LG", "extractor": "disk", "matcher": "lightglue-disk", "in_paper": True},
    "loftr": {"paper_name": "LoFTR", "extractor": None, "matcher": "loftr-outdoor", "in_paper": True},
    "sp-lg": {"paper_name": "SP+LG", "extractor": "superpoint", "matcher": "lightglue-superpoint", "in_paper": False},
    "aliked-nn": {"paper_name": "ALIKED+NN", "extractor": "aliked", "matcher": "nn-mutual", "in_paper": False},
    "aliked-lg": {"paper_name": "ALIKED+LG", "extractor": "aliked", "matcher": "lightglue-aliked", "in_paper": False},
    "xfeat-nn": {"paper_name": "XFeat+NN", "extractor": "xfeat", "matcher": "nn-mutual", "in_paper": False},
    "xfeat-lg": {
        "paper_name": "XFeat+LighterGlue",
        "extractor": "xfeat",
        "matcher": "lighterglue-xfeat",
        "in_paper": False,
    },
    "orb-nn": {"paper_name": "ORB+NN", "extractor": "orb", "matcher": "nn-hamming", "in_paper": False},
    "sift-opencv-nn": {
        "paper_name": "SIFT (OpenCV)+NN",
        "extractor": "sift-opencv",
        "matcher": "nn-ratio",
        "in_paper": False,
    },
}

# The GV-Bench repository's current evaluation (main.py, config/*.yaml and its fork of
# image-matching-models, branch gvbench): every image read as RGB with PIL and resized to a
# fixed 512x288 (width x height) by torchvision's antialiased bilinear Resize, then each
# matcher with the fork's own defaults (2048 keypoints for the sparse ones).
REPOSITORY_IMAGE_SIZE = (512, 288)
_REPOSITORY_IMAGE = {
    "resize_to": list(REPOSITORY_IMAGE_SIZE),
    "resize_max": None,
    "resize_force": False,
    "interpolation": "bilinear_antialias",
    "store_float16": False,
}
# The fork's sift-nn is OpenCV SIFT with its own defaults (contrastThreshold 0.04 = peak
# 0.04 / 3 layers), plain SIFT descriptors, on the min-max stretched grey image it makes; so
# under this profile the `sift` extractor is OpenCV's, not COLMAP's.
_REPOSITORY_SIFT = {
    **_REPOSITORY_IMAGE,
    "max_keypoints": 2048,
    "peak_threshold": 0.04 / 3,
    "root_sift": False,
    "normalize_minmax": True,
    "uint8": "truncate",
}
# LightGlue's extractors (cvg/lightglue, which the fork calls) resize their input again,
# longest side to 1024 (so 512x288 runs at 1024x576), and map keypoints back.
_LIGHTGLUE_INPUT = {"model_input_long_side": 1024}

# Profile -> overrides, keyed by extractor or matcher type, then by conf name (the more
# specific, applied last). 'paper' is the protocol as published (the hloc chain, MODELS.md
# section 1); 'repository' is the GV-Bench repository's current code, the cheap profile whose
# numbers compare with that repository's published table (reference_values).
PROFILES: dict[str, dict[str, dict[str, Any]]] = {
    "paper": {},
    "repository": {
        "sift": {**_REPOSITORY_SIFT, "type": "opencv_sift"},
        "opencv_sift": _REPOSITORY_SIFT,
        "orb": {**_REPOSITORY_IMAGE, "max_keypoints": 2048, "normalize_minmax": True, "uint8": "truncate"},
        "disk": {**_REPOSITORY_IMAGE, **_LIGHTGLUE_INPUT, "max_keypoints": 2048},
        # LightGlue's SuperPoint defaults: NMS 4, detection threshold 0.0005, borders 4.
        "superpoint": {
            **_REPOSITORY_IMAGE,
            **_LIGHTGLUE_INPUT,
            "max_keypoints": 2048,
            "resize_force": False,
            "nms_radius": 4,
            "keypoint_threshold": 0.0005,
        },
        "aliked": {**_REPOSITORY_IMAGE, **_LIGHTGLUE_INPUT, "max_keypoints": 2048},
        # The fork's 'xfeat' is XFeat sparse, mutual nearest neighbour (min_cossim -1): xfeat-nn.
        "xfeat": {**_REPOSITORY_IMAGE, "max_keypoints": 2048},
        # The fork's LoFTR verifies each pair's raw matches: no merging across pairs.
        "loftr": {**{k: v for k, v in _REPOSITORY_IMAGE.items() if k != "store_float16"}, "merge_max_keypoints": None},
        # The fork's sift-nn / orb-nn: OpenCV BFMatcher k=2 on the raw descriptors, kept when
        # m.distance < 0.75 n.distance (strict), no mutual check (disk-nn, which the repository
        # does not run, shares sift-nn's matcher conf).
        "nn-ratio": {"ratio_threshold": 0.75, "mutual": False, "rule": "knn_ratio"},
        "nn-hamming": {"ratio_threshold": 0.75, "mutual": False, "rule": "knn_ratio"},
        # The fork's LightGlue runs without adaptive depth or width (both -1); its xfeat-lg
        # is XFeat's own LighterGlue call, with that model's settings.
        **{
            name: {"depth_confidence": -1, "width_confidence": -1}
            for name in ("lightglue-disk", "lightglue-superpoint", "lightglue-aliked")
        },
    },
}
# Profiles this package used to have, and what replaced them.
REPLACED_PROFILES: dict[str, str] = {"fast": "repository"}

# Verification after the score filter (which matters for SG, LG, LoFTR). ``few_matches`` is
# what a pair scores when it has fewer than ``min_matches`` matches or RANSAC finds no model:
# "zero" (no inliers) is the rule of the benchmark's released evaluation code (May 2024 on);
# "all" (every match counted as an inlier) is that of the code of the paper's submission
# period (Jan-Mar 2024). Which one produced the published table is not stated; the paper
# profile keeps the released code's rule, the one anyone rerunning the benchmark gets, and
# because a pair too poor to verify should not score by its raw match count.
# ``coordinates``: "original" fits F on keypoints in original pixels (hloc stores them so);
# "resize_to" maps them first into the fixed ``resize_to`` frame the repository's code fits in.
VERIFIER: dict[str, Any] = {
    "type": "fundamental",
    "method": "FM_RANSAC",
    "threshold_px": 3.0,
    "confidence": 0.99,
    "max_iters": 1000,
    "min_matches": 8,
    "few_matches": "zero",
    "min_match_score": 0.5,
    "coordinates": "original",
}
VERIFIER_PROFILES: dict[str, dict[str, Any]] = {
    "paper": {},
    # main.py's ransac_kwargs; the fork's BaseMatcher.process_matches counts every match when
    # fewer than 8 (4 before its commit of 2025-01-11) and applies no score filter.
    "repository": {
        "confidence": 0.95,
        "max_iters": 2000,
        "few_matches": "all",
        "min_match_score": None,
        "coordinates": "resize_to",
        "resize_to": list(REPOSITORY_IMAGE_SIZE),
    },
}


UnknownNameError = registry.UnknownNameError


def _unknown(kind: str, name: str, known: list[str]) -> UnknownNameError:
    return UnknownNameError(registry.unknown_name_message(kind, name, known))


def check_profile(profile: str) -> None:
    if profile in REPLACED_PROFILES and profile not in PROFILES:
        raise UnknownNameError(
            f"profile {profile!r} was replaced by {REPLACED_PROFILES[profile]!r} (the GV-Bench repository's "
            f"current protocol); set profile: {REPLACED_PROFILES[profile]} or paper"
        )
    if profile not in PROFILES:
        raise _unknown("profile", profile, list(PROFILES))


def profile_overrides(profile: str, conf: dict[str, Any], name: str) -> dict[str, Any]:
    """The overrides a profile makes to one extractor or matcher conf: by type, then by name."""
    overrides = PROFILES[profile]
    return {**overrides.get(conf["type"], {}), **(overrides.get(name, {}) if name != conf["type"] else {})}


def _component(
    kind: str, entry: str | dict[str, Any], table: dict[str, dict[str, Any]], profile: str, method: str
) -> dict[str, Any]:
    """An extractor or matcher conf under a profile: a conf name from ``table``, or a conf dict
    written in the method entry itself (named after the method unless it has a ``name``)."""
    if isinstance(entry, dict):
        conf, name = copy.deepcopy(entry), str(entry.get("name", method))
    else:
        conf, name = copy.deepcopy(registry.lookup(kind, entry, table, f"method {method!r}")), entry
    conf.setdefault("checkpoints", [])
    conf.update(profile_overrides(profile, conf, name))
    conf["name"] = name
    return conf


def component_name(entry: str | dict[str, Any] | None) -> str:
    """How ``methods`` lists a method's extractor or matcher."""
    if entry is None:
        return "(dense)"
    return entry if isinstance(entry, str) else str(entry.get("name", entry["type"]))


def register_method(
    name: str,
    extractor: str | dict[str, Any] | None,
    matcher: str | dict[str, Any],
    paper_name: str | None = None,
    in_paper: bool = False,
) -> None:
    """Add a method: ``extractor`` and ``matcher`` are conf names (``EXTRACTORS``, ``MATCHERS``) or
    conf dicts whose ``type`` is a registered type or a ``"package.module:Class"`` reference.
    A method of the package is one entry in ``METHODS``; this is the same entry made from code."""
    if name in METHODS or imm.is_imm(name) or name in ("all", "all-available"):
        raise ValueError(f"method name {name!r} is taken; choose another name")
    for kind, entry in (("extractor", extractor), ("matcher", matcher)):
        if isinstance(entry, dict) and "type" not in entry:
            raise ValueError(f"method {name!r}: the {kind} conf needs a 'type' (a registered type or 'module:Class')")
    METHODS[name] = {"paper_name": paper_name or name, "extractor": extractor, "matcher": matcher, "in_paper": in_paper}


def _is_number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


def _is_whole(value: Any) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


# Numeric verifier keys: (check, what the value must be). OpenCV does not refuse values out
# of range: a threshold of 0 or less silently becomes its 3 px default, for one.
VERIFIER_RANGES: dict[str, tuple[Any, str]] = {
    "threshold_px": (lambda v: _is_number(v) and v > 0, "a number of pixels above 0"),
    "confidence": (lambda v: _is_number(v) and 0 < v < 1, "a number between 0 and 1 (both excluded)"),
    # OpenCV takes an int: above 2**31 - 1 it would fail mid-run.
    "max_iters": (lambda v: _is_whole(v) and 1 <= v <= 2**31 - 1, "a whole number from 1 to 2147483647"),
    "min_matches": (lambda v: _is_whole(v) and v >= 0, "a whole number of at least 0"),
    "min_match_score": (lambda v: v is None or _is_number(v), "a number or null (null keeps every match)"),
    "resize_to": (
        lambda v: isinstance(v, (list, tuple)) and len(v) == 2 and all(_is_whole(x) and x >= 1 for x in v),
        "[width, height], two whole numbers of at least 1",
    ),
}


def check_verifier_overrides(overrides: dict[str, Any]) -> None:
    """Overrides of the run's verifier name its keys; the model and estimator are known ones;
    numeric values are in range (``VERIFIER_RANGES``)."""
    unknown = [key for key in overrides if key not in VERIFIER and key != "resize_to"]
    if unknown:
        raise ValueError(
            f"unknown key(s) {registry.unknown_keys_hint(unknown, list(VERIFIER))}; valid: {', '.join(VERIFIER)}"
        )
    for key, (check, what) in VERIFIER_RANGES.items():
        if key in overrides and not check(overrides[key]):
            raise ValueError(f"{key} must be {what}, got {overrides[key]!r}")
    if "coordinates" in overrides:
        registry.check_choice("verifier coordinates", overrides["coordinates"], ("original", "resize_to"))
    if not {"type", "method", "few_matches"} & set(overrides):
        return
    from gvbench_nb.protocol import ransac  # imports OpenCV: only when a choice is to be checked

    if "type" in overrides:
        registry.check_choice("verifier model", overrides["type"], ransac.MODELS)
    if "method" in overrides:
        registry.check_choice("estimator", overrides["method"], ransac.ESTIMATORS)
    if "few_matches" in overrides:
        registry.check_choice("few_matches rule", overrides["few_matches"], ransac.FEW_MATCHES_RULES)


def resolve_method(name: str, profile: str = "paper", verifier: dict[str, Any] | None = None) -> dict[str, Any]:
    """The full conf of a method under a profile: name, extractor, matcher, verifier.

    ``verifier``: overrides of the profile's verifier conf (the params' ``verifier`` key), so a
    stronger verifier than the paper's reaches ``pairs.csv`` and ``results.csv``; the verifier
    conf is part of the match folder's hash, so its results never mix with the default's.

    ``imm:<name>`` is vismatch's matcher ``<name>`` run as a pair matcher (``imm.py``); a
    profile's ``imm`` entry overrides its image preparation."""
    if imm.is_imm(name):
        check_profile(profile)
        extractor = None
        matcher = imm.matcher_conf(name, PROFILES[profile].get("imm"))
        paper_name = imm.paper_name(name)
    else:
        if name not in METHODS:
            raise _unknown("method", name, list(METHODS))
        check_profile(profile)
        method = METHODS[name]
        paper_name = method["paper_name"]
        extractor = None  # dense matchers (LoFTR) have none: they cannot use the per-image cache
        if method["extractor"] is not None:
            extractor = _component("extractor", method["extractor"], EXTRACTORS, profile, name)
        matcher = _component("matcher", method["matcher"], MATCHERS, profile, name)
    return {
        "method": name,
        "paper_name": paper_name,
        "profile": profile,
        "extractor": extractor,
        "matcher": matcher,
        "verifier": {
            **copy.deepcopy(VERIFIER),
            **copy.deepcopy(VERIFIER_PROFILES[profile]),
            **copy.deepcopy(verifier or {}),
        },
    }


def is_dense(conf: dict[str, Any]) -> bool:
    """A resolved method whose matcher takes two images (LoFTR, vismatch's pair matchers):
    it has no extractor, so nothing is cached per image and its matcher prepares the images."""
    return conf["extractor"] is None


def paper_name(name: str) -> str:
    """The name a method goes by in tables: its paper name, ``vismatch <name>``
    for ``imm:`` methods, else the name itself."""
    if imm.is_imm(name):
        return imm.paper_name(name)
    return METHODS.get(name, {}).get("paper_name", name)


def conf_hash(conf: dict[str, Any]) -> str:
    """Short stable hash of a conf (its cache identity)."""
    return hashlib.sha1(json.dumps(conf, sort_keys=True).encode()).hexdigest()[:10]


def required_checkpoints(name: str, profile: str = "paper") -> list[str]:
    """Our checkpoints a method needs (``imm:`` methods: none of ours; ``imm.require`` checks theirs)."""
    conf = resolve_method(name, profile)
    extractor_checkpoints = conf["extractor"]["checkpoints"] if conf["extractor"] else []
    return list(dict.fromkeys(extractor_checkpoints + conf["matcher"]["checkpoints"]))


def method_table() -> list[dict[str, Any]]:
    """One row a method for ``python -m gvbench_nb methods``."""
    rows = []
    for name, method in METHODS.items():
        needed = required_checkpoints(name)
        missing = [c for c in needed if not weights.is_present(c)]
        rows.append(
            {
                "method": name,
                "paper_name": method["paper_name"],
                "in_paper": method["in_paper"],
                "extractor": component_name(method["extractor"]),
                "matcher": component_name(method["matcher"]),
                "weights": ", ".join(needed) or "-",
                "available": not missing,
                "missing": ", ".join(weights.get(c).file for c in missing),
            }
        )
    return rows


def require(name: str, profile: str = "paper") -> None:
    """Fail before any work when a method's weights (or, for ``imm:``, vismatch) are missing."""
    weights.require(*required_checkpoints(name, profile))
    if imm.is_imm(name):
        imm.require(name)


def available_methods() -> list[str]:
    return [row["method"] for row in method_table() if row["available"]]


def expand_methods(names: list[str] | str) -> list[str]:
    """Method names from a list or a comma string; ``all`` and ``all-available`` expand."""
    if isinstance(names, str):
        names = [n.strip() for n in names.split(",") if n.strip()]
    expanded: list[str] = []
    for name in names:
        if name == "all":
            expanded.extend(METHODS)
        elif name == "all-available":
            expanded.extend(available_methods())
        elif name in METHODS:
            expanded.append(name)
        elif imm.is_imm(name):
            imm.check_name(name)
            expanded.append(name)
        else:
            raise _unknown("method", name, list(METHODS) + ["all", "all-available", "imm:<vismatch name>"])
    return list(dict.fromkeys(expanded))
