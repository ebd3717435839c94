"""The recipes: one table a profile (``paper.yaml``, ``repository.yaml``), each method written whole
(``paper_name``, ``in_paper``, ``extractor``, ``matcher``, ``verifier``) under the reference it
reproduces; nothing is merged or overridden."""

from __future__ import annotations

import copy
import hashlib
import json
from pathlib import Path
from typing import Any

import yaml

from gvbench_nb.protocol import registry

RECIPE_KEYS = ("paper_name", "in_paper", "extractor", "matcher", "verifier")


def _load(profile: str) -> dict[str, dict[str, Any]]:
    table: dict[str, dict[str, Any]] = yaml.safe_load((Path(__file__).parent / f"{profile}.yaml").read_text())
    for name, recipe in table.items():
        if tuple(recipe) != RECIPE_KEYS:
            raise ValueError(f"recipes/{profile}.yaml: {name} has keys {list(recipe)}, not {list(RECIPE_KEYS)}")
    return table


# profile -> method -> recipe. 'paper' is the protocol as published (the hloc chain); 'repository'
# the GV-Bench repository's current code, whose numbers compare with its published table.
RECIPES: dict[str, dict[str, dict[str, Any]]] = {profile: _load(profile) for profile in ("paper", "repository")}


def check_profile(profile: str) -> None:
    if profile not in RECIPES:
        raise registry.UnknownNameError(registry.unknown_name_message("profile", profile, list(RECIPES)))


def recipe(name: str, profile: str = "paper") -> dict[str, Any]:
    """A copy of the whole recipe of ``name`` under ``profile``."""
    check_profile(profile)
    if name not in RECIPES[profile]:
        raise registry.UnknownNameError(registry.unknown_name_message("method", name, list(RECIPES[profile])))
    return copy.deepcopy(RECIPES[profile][name])


def profile_verifier(profile: str) -> dict[str, Any]:
    """A copy of the verifier every recipe of ``profile`` writes (its first recipe's)."""
    check_profile(profile)
    return copy.deepcopy(next(iter(RECIPES[profile].values()))["verifier"])


def conf_hash(conf: dict[str, Any]) -> str:
    """Short stable hash of a conf (its cache identity)."""
    return hashlib.sha1(json.dumps(conf, sort_keys=True).encode()).hexdigest()[:10]
