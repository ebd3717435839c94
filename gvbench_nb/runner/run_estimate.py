"""What a run will take, said before it starts: the work its caches lack times measured costs.

A method's cost is seconds an image to extract plus seconds a pair to match and verify. They are
the timers of what the caches already hold where there are any, else ``measured_costs.csv``: the
per-image and per-pair timers of dated runs on a 2-core CPU (docs/results.md).
"""

from __future__ import annotations

import functools
from pathlib import Path
from typing import Any

import pandas as pd

from gvbench_nb import methods as method_registry
from gvbench_nb.data.sequences import Sequence
from gvbench_nb.runner import image_features, pair_matching
from gvbench_nb.runner.store import ShardedStore

MEASURED_COSTS = Path(__file__).resolve().with_name("measured_costs.csv")
LONG_RUN_SECONDS = 300.0  # a longer run says so in its first lines, with its estimate


def run_seconds(n_images: float, seconds_per_image: float, n_pairs: float, seconds_per_pair: float) -> float:
    """The cost model: each image extracted once, each pair matched and verified once."""
    return n_images * seconds_per_image + n_pairs * seconds_per_pair


@functools.cache
def measured_costs() -> dict[tuple[str, str], tuple[float, float]]:
    """(method, profile) -> (seconds an image, seconds a pair) from ``measured_costs.csv``."""
    table = pd.read_csv(MEASURED_COSTS)
    return {(r.method, r.profile): (r.seconds_per_image, r.seconds_per_pair) for r in table.itertuples()}


def _missing_and_mean(store: ShardedStore, keys: set[str], timers: tuple[str, ...]) -> tuple[int, float | None]:
    """How many of ``keys`` the store lacks, and the mean of ``timers`` summed over those it holds."""
    store.refresh()
    held = [key for key in keys if key in store]
    seconds = [sum(float(store.read(key, fields=())[f"attr:{t}"]) for t in timers) for key in held]
    store.close()
    return len(keys) - len(held), (sum(seconds) / len(seconds) if seconds else None)


def method_seconds(
    sequence: Sequence, conf: dict[str, Any], cache_dir: Path, seed: int, counted: set[str]
) -> float | None:
    """Seconds ``conf`` will take on what the caches lack; None without a cost to go by. ``counted``:
    feature folders an earlier method of the run extracts, whose images this one finds cached."""
    per_image, per_pair = measured_costs().get((conf["method"], conf["profile"]), (None, None))
    images = 0
    if not method_registry.is_dense(conf):
        store = image_features.feature_store(cache_dir, conf["extractor"])
        contents = image_features.content_keys(sequence, cache_dir)
        missing, cached_per_image = _missing_and_mean(store, contents, ("seconds",))
        images = 0 if str(store.folder) in counted else missing
        per_image = cached_per_image or per_image
        counted.add(str(store.folder))
    keys = pair_matching.pair_keys(sequence, seed)
    pairs, cached_per_pair = _missing_and_mean(
        pair_matching.match_store(cache_dir, conf, keys), set(keys.values()), ("match_seconds", "verify_seconds")
    )
    per_pair = cached_per_pair or per_pair
    if (images and per_image is None) or (pairs and per_pair is None):
        return None
    return run_seconds(images, per_image or 0.0, pairs, per_pair or 0.0)


def long_run_note(params: dict[str, Any], sequence: Sequence) -> str | None:
    """The line a run prints first when its estimate exceeds ``LONG_RUN_SECONDS``; None otherwise."""
    counted: set[str] = set()
    estimates = {}
    for method in params["methods"]:
        conf = method_registry.resolve_method(method, params["profile"], params.get("verifier") or None)
        estimates[method] = method_seconds(sequence, conf, Path(params["cache_dir"]), params["seed"], counted)
    total = sum(seconds for seconds in estimates.values() if seconds is not None)
    if total <= LONG_RUN_SECONDS:
        return None
    each = ", ".join(f"{m} {minutes(s)}" for m, s in estimates.items() if s is not None)
    unknown = [m for m, s in estimates.items() if s is None]
    return (
        f"note: this run is estimated at {minutes(total)} ({each}"
        + (f"; no measured cost for {', '.join(unknown)}" if unknown else "")
        + ") from costs measured on a 2-core CPU; --methods or --limit N makes it shorter"
    )


def minutes(seconds: float) -> str:
    """``seconds`` as a person reads a run's length: minutes, or hours from one and a half."""
    if seconds >= 5400:
        return f"{seconds / 3600:.1f} hours"
    count = max(1, round(seconds / 60))
    return f"{count} minute{'s' if count > 1 else ''}"
