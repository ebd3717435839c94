"""The method catalogue: a recipe of ``protocol/recipes/<profile>.yaml`` or ``imm:<name>``
(vismatch's matcher via ``benchmarks/imm.py``); resolves names, verifier overrides, weights, ``all``."""

from __future__ import annotations

import copy
import importlib
import importlib.util
import itertools
import math
import sys
from pathlib import Path
from types import ModuleType
from typing import Any

from gvbench_nb import GVBenchError
from gvbench_nb.io_utils import is_whole_number, unknown_keys_hint
from gvbench_nb.protocol import recipes, registry, weights
from gvbench_nb.protocol.recipes import RECIPES, check_profile, conf_hash

__all__ = ["RECIPES", "check_profile", "conf_hash"]

IMM_PREFIX = "imm:"  # a vismatch matcher, run by the peer module benchmarks/imm.py


def is_imm(name: str) -> bool:
    return name.startswith(IMM_PREFIX)


def imm_peer() -> ModuleType:
    """The vismatch peer, ``benchmarks/imm.py`` beside the package: loaded on the first ``imm:`` method."""
    name = "benchmarks.imm"
    if name not in sys.modules:
        path = Path(__file__).resolve().parents[1] / "benchmarks" / "imm.py"
        spec = importlib.util.spec_from_file_location(name, path)
        if spec is None or spec.loader is None or not path.is_file():
            return importlib.import_module(name)
        sys.modules[name] = module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
    return sys.modules[name]


# Methods added by ``register_method`` in this process: only this process knows them.
REGISTERED_FROM_CODE: set[str] = set()


def method_names() -> list[str]:
    """Every method of the recipes, in the paper table's order (then the repository's own)."""
    return list(dict.fromkeys(name for table in RECIPES.values() for name in table))


def verifier_keys() -> list[str]:
    """The verifier conf's keys, as the recipes write them."""
    return list(dict.fromkeys(key for table in RECIPES.values() for r in table.values() for key in r["verifier"]))


def register_method(name: str, profiles: dict[str, dict[str, Any]]) -> None:
    """Add a method from code: ``profiles`` maps a profile to its whole recipe there (the keys of
    ``recipes.RECIPE_KEYS``; ``paper_name``, ``in_paper`` optional), as a recipe file's entry would."""
    if name in method_names() or is_imm(name) or name in ("all", "all-available"):
        raise ValueError(f"method name {name!r} is taken; choose another name")
    for profile, entry in profiles.items():
        check_profile(profile)
        for kind in ("extractor", "matcher"):
            conf = entry.get(kind)
            if isinstance(conf, dict) and "type" not in conf:
                raise ValueError(
                    f"method {name!r}: the {kind} conf needs a 'type' (a registered type or 'module:Class')"
                )
        if entry.get("matcher") is None:
            raise ValueError(f"method {name!r}: a recipe needs a matcher conf")
    for profile, entry in profiles.items():
        whole = {"paper_name": name, "in_paper": False, "extractor": None, **copy.deepcopy(entry)}
        for kind in ("extractor", "matcher"):
            if whole[kind] is not None:
                whole[kind].setdefault("name", name)
                whole[kind].setdefault("checkpoints", [])
        whole.setdefault("verifier", recipes.profile_verifier(profile))
        RECIPES[profile][name] = {key: whole[key] for key in recipes.RECIPE_KEYS}
    REGISTERED_FROM_CODE.add(name)


class ProcessOnlyMethodError(GVBenchError):
    """A method registered from code, asked of a command that computes in other processes."""


def check_known_to_kernels(names: list[str]) -> None:
    """``run`` executes its notebooks in fresh kernels (and Dask workers in other processes),
    which know the recipe files' methods, not those ``register_method`` added here: refused
    in one sentence before any work rather than failing in a kernel."""
    mine = [name for name in names if name in REGISTERED_FROM_CODE]
    if mine:
        raise ProcessOnlyMethodError(
            f"method {', '.join(mine)} was registered from code (methods.register_method), and run executes "
            "its notebooks in fresh kernels that know only the methods of gvbench_nb/protocol/recipes/: "
            "compute it in this process with method_runs.run_method, or add it there as an entry a profile "
            "(docs/extending.md)"
        )


def _is_number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


# Numeric verifier keys: (check, what the value must be). OpenCV does not refuse values out
# of range: a threshold of 0 or less silently becomes its 3 px default, for one.
VERIFIER_RANGES: dict[str, tuple[Any, str]] = {
    "threshold_px": (lambda v: _is_number(v) and v > 0, "a number of pixels above 0"),
    "confidence": (lambda v: _is_number(v) and 0 < v < 1, "a number between 0 and 1 (both excluded)"),
    # OpenCV takes an int: above 2**31 - 1 it would fail mid-run.
    "max_iters": (lambda v: is_whole_number(v) and 1 <= v <= 2**31 - 1, "a whole number from 1 to 2147483647"),
    "min_matches": (lambda v: is_whole_number(v) and v >= 0, "a whole number of at least 0"),
    "min_match_score": (lambda v: v is None or _is_number(v), "a number or null (null keeps every match)"),
    "resize_to": (
        lambda v: isinstance(v, (list, tuple)) and len(v) == 2 and all(is_whole_number(x) and x >= 1 for x in v),
        "[width, height], two whole numbers of at least 1",
    ),
}


def check_verifier_overrides(overrides: dict[str, Any]) -> None:
    """Overrides of the run's verifier: known keys and choices, numbers in range (``VERIFIER_RANGES``)."""
    unknown = [key for key in overrides if key not in verifier_keys()]
    if unknown:
        raise ValueError(
            f"unknown key(s) {unknown_keys_hint(unknown, verifier_keys())}; valid: {', '.join(verifier_keys())}"
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
    """A method's recipe under a profile with the run's ``verifier`` overrides (part of the match
    folder's hash, so their results never mix with the default's)."""
    check_profile(profile)
    whole: dict[str, Any]
    if is_imm(name):
        peer = imm_peer()
        whole = {"paper_name": peer.paper_name(name), "extractor": None, "matcher": peer.matcher_conf(name, None)}
        base_verifier = recipes.profile_verifier(profile)
    else:
        if name not in RECIPES[profile]:
            known = method_names()
            if name in known:
                raise registry.UnknownNameError(f"method {name!r} has no recipe under profile {profile!r}")
            raise registry.UnknownNameError(registry.unknown_name_message("method", name, known))
        whole = recipes.recipe(name, profile)
        base_verifier = whole["verifier"]
    return {
        "method": name,
        "paper_name": whole["paper_name"],
        "profile": profile,
        "extractor": whole["extractor"],
        "matcher": whole["matcher"],
        "verifier": {**base_verifier, **copy.deepcopy(verifier or {})},
    }


def reference_lines(name: str, profile: str) -> list[str]:
    """The comment lines a profile's recipe file holds for ``name``: the file's header (its sources
    and the verifier every recipe shares), then the references written above the recipe itself."""
    check_profile(profile)
    lines = (Path(recipes.__file__).parent / f"{profile}.yaml").read_text().splitlines()
    header = list(itertools.takewhile(lambda line: line.startswith("#"), lines))
    start = lines.index(f"{name}:") + 1 if f"{name}:" in lines else len(lines)
    own = [line.strip() for line in itertools.takewhile(lambda line: line.strip().startswith("#"), lines[start:])]
    return [*header, *own]


def is_dense(conf: dict[str, Any]) -> bool:
    """A resolved method whose matcher takes two images (LoFTR, vismatch's pair matchers):
    it has no extractor, so nothing is cached per image and its matcher prepares the images."""
    return conf["extractor"] is None


def paper_name(name: str) -> str:
    """The name a method goes by in tables: its paper name, ``vismatch <name>`` for ``imm:`` methods, else itself."""
    if is_imm(name):
        return imm_peer().paper_name(name)
    return RECIPES["paper"].get(name, {}).get("paper_name", name)


def required_checkpoints(name: str, profile: str = "paper") -> list[str]:
    """Our checkpoints a method needs (``imm:`` methods: none of ours; the peer's ``require`` checks theirs)."""
    conf = resolve_method(name, profile)
    extractor_checkpoints = conf["extractor"]["checkpoints"] if conf["extractor"] else []
    return list(dict.fromkeys(extractor_checkpoints + conf["matcher"]["checkpoints"]))


def method_table() -> list[dict[str, Any]]:
    """One row a method for ``python -m gvbench_nb methods``."""
    rows = []
    for name in method_names():
        method = RECIPES["paper"][name]
        needed = required_checkpoints(name)
        missing = [c for c in needed if not weights.is_present(c)]
        rows.append(
            {
                "method": name,
                "paper_name": method["paper_name"],
                "in_paper": method["in_paper"],
                "extractor": method["extractor"]["name"] if method["extractor"] else "(dense)",
                "matcher": method["matcher"]["name"],
                "weights": ", ".join(needed) or "-",
                "available": not missing,
                "missing": ", ".join(weights.get(c).file for c in missing),
            }
        )
    return rows


def require(name: str, profile: str = "paper") -> None:
    """Fail before any work when a method's weights (or, for ``imm:``, vismatch) are missing."""
    weights.require(*required_checkpoints(name, profile))
    if is_imm(name):
        imm_peer().require(name)


def expand_methods(names: list[str] | str) -> list[str]:
    """Method names from a list or a comma string; ``all`` and ``all-available`` expand."""
    if isinstance(names, str):
        names = [n.strip() for n in names.split(",") if n.strip()]
    expanded: list[str] = []
    for name in names:
        if name == "all":
            expanded.extend(method_names())
        elif name == "all-available":
            expanded.extend(row["method"] for row in method_table() if row["available"])
        elif name in method_names():
            expanded.append(name)
        elif is_imm(name):
            imm_peer().check_name(name)
            expanded.append(name)
        else:
            known = method_names() + ["all", "all-available", "imm:<vismatch name>"]
            raise registry.UnknownNameError(registry.unknown_name_message("method", name, known))
    return list(dict.fromkeys(expanded))
