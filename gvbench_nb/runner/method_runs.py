"""Run one method on a sequence: compute (resumable), record what was computed, write its table."""

from __future__ import annotations

import functools
import hashlib
import json
import time
from collections import Counter
from pathlib import Path
from typing import Any

import pandas as pd

from gvbench_nb import __version__
from gvbench_nb import methods as method_registry
from gvbench_nb.data.sequences import Sequence
from gvbench_nb.io_utils import atomic_write_csv, atomic_write_json
from gvbench_nb.protocol import weights
from gvbench_nb.runner import concurrency, config, image_features, method_outputs, pair_matching, runs, scoring


def pairs_table(sequence: Sequence, conf: dict[str, Any], cache_dir: Path, seed: int) -> pd.DataFrame:
    """The per-pair table of a finished run, built only from the stores."""
    keys = pair_matching.pair_keys(sequence, seed)
    matches = pair_matching.match_store(cache_dir, conf, keys)
    matches.refresh()
    dense = method_registry.is_dense(conf)
    uses = Counter(name for pair in sequence.pairs for name in (pair.query, pair.reference))
    image_info: dict[str, tuple[int, float]] = {}
    if not dense:
        features = image_features.feature_store(cache_dir, conf["extractor"])
        features.refresh()
        for name in uses:
            key = image_features.image_key(sequence.image_root, name)
            entry = features.read(key, fields=("keypoints",))  # not descriptors
            image_info[name] = (len(entry["keypoints"]), float(entry["attr:seconds"]))
        features.close()
    rows = []
    for index, pair in enumerate(sequence.pairs):
        entry = pair_matching.stored_counts(matches, keys[pair])  # the counts and timers only
        if dense:  # a dense matcher's keypoints are its matches; its whole cost is matching
            keypoints_query = keypoints_reference = int(entry["attr:num_matches"])
            extract_seconds = 0.0
        else:
            keypoints_query, keypoints_reference = image_info[pair.query][0], image_info[pair.reference][0]
            # Extraction is amortised: each image's time is shared among the pairs that use it.
            extract_seconds = sum(image_info[n][1] / uses[n] for n in (pair.query, pair.reference))
        rows.append(
            {
                "pair_index": index,
                "query": pair.query,
                "reference": pair.reference,
                "label": pair.label,
                "method": conf["method"],
                "profile": conf["profile"],
                "num_keypoints_query": keypoints_query,
                "num_keypoints_reference": keypoints_reference,
                "num_matches": int(entry["attr:num_matches"]),
                "num_matches_filtered": int(entry["attr:num_matches_filtered"]),
                "num_inliers": int(entry["attr:num_inliers"]),
                **{name: int(entry[f"attr:{name}"]) for name in method_outputs.INLIER_KEYPOINT_COUNTS},
                "score": int(entry["attr:num_inliers"]),
                "extract_seconds": extract_seconds,
                "match_seconds": float(entry["attr:match_seconds"]),
                "verify_seconds": float(entry["attr:verify_seconds"]),
            }
        )
    matches.close()
    return pd.DataFrame(rows, columns=method_outputs.PAIRS_COLUMNS)


def result_identity(sequence: Sequence, conf: dict[str, Any], seed: int, device: str) -> dict[str, Any]:
    """What a finished result stands for, as its ``run.json`` records it: inputs, conf, seed, device asked for."""
    identity = {
        "sequence": sequence.name,
        "image_root": str(sequence.image_root),
        "binding": scoring.sequence_binding(sequence),
        "conf": conf,
        "seed": seed,
        "device_request": str(device),
    }
    return json.loads(json.dumps(identity, default=str))  # as it reads back from JSON


def finished_table(
    folder: Path, sequence: Sequence, conf: dict[str, Any], seed: int, device: str
) -> pd.DataFrame | None:
    """The per-pair table ``folder`` holds when its result is of these inputs (``result_identity``), else None."""
    try:
        run = method_outputs.read_run_json(folder.parent, folder.name)
        identity = result_identity(sequence, conf, seed, device)
    except (OSError, ValueError):  # no result, or an image gone: the work names it and its pair
        return None
    done = isinstance(run, dict) and all(run.get(key) == value for key, value in identity.items())
    if not done or not (folder / "pairs.csv").is_file():
        return None
    table = pd.read_csv(folder / "pairs.csv", keep_default_na=False)
    # A table missing a column the package writes (its inlier keypoint counts) is made again from the stores.
    return table if set(method_outputs.PAIRS_COLUMNS) <= set(table.columns) else None


def compute_method(
    sequence: Sequence,
    conf: dict[str, Any],
    cache_dir: Path,
    device: str = "auto",
    seed: int = 0,
    progress: bool = True,
    threads: int | None = None,
    jobs: int | None = None,
    run_id: str | None = None,
) -> dict[str, Any]:
    """Extract and match what the caches lack (the work of ``run_method`` and of a shard, nothing
    written); ``run.json``'s ``environment`` and ``this_run``."""
    from gvbench_nb.protocol.features.base import resolve_device

    resolved_device = resolve_device(device)
    jobs = concurrency.job_count(jobs)
    # Dense matchers take one pair at a time: their one job gets every core's OpenCV threads.
    threads = concurrency.configure_threads(threads, 1 if method_registry.is_dense(conf) else jobs)
    started = time.perf_counter()
    extraction = {"images": 0, "cached": 0, "extracted": 0}  # a dense matcher extracts nothing
    if conf["extractor"]:
        extraction = image_features.extract_features(
            sequence, conf["extractor"], cache_dir, resolved_device, progress, jobs=jobs, run_id=run_id
        )
    extracted = time.perf_counter()
    matching = pair_matching.match_and_verify(sequence, conf, cache_dir, resolved_device, seed, progress, jobs=jobs)
    finished = time.perf_counter()
    return {
        "environment": concurrency.environment_info(resolved_device),
        "this_run": {
            "extraction": extraction,
            "matching": matching,
            "jobs": jobs,
            "threads": threads,
            "extract_wall_seconds": extracted - started,
            "match_verify_wall_seconds": finished - extracted,
        },
    }


def run_method(
    sequence: Sequence,
    method: str,
    profile: str,
    output_dir: Path,
    cache_dir: Path,
    device: str = "auto",
    seed: int = 0,
    verifier: dict[str, Any] | None = None,
    params: dict[str, Any] | None = None,
    **options: Any,
) -> pd.DataFrame:
    """Run one method on a sequence end to end (``pairs.csv``, ``run.json``); a finished result of the
    same inputs is returned as it is, and cached work is reused, so an interrupted run resumes."""
    conf = method_registry.resolve_method(method, profile, verifier)
    method_registry.require(method, profile)
    if runs.is_run(output_dir):  # a run's stage notebook: the run computed the method already
        done = finished_table(method_outputs.method_dir(output_dir, method), sequence, conf, seed, device)
        if done is not None:
            return done
        work = compute_method(sequence, conf, cache_dir, device, seed, run_id=runs.run_id(output_dir), **options)
        return write_results(output_dir, sequence, conf, seed, work["environment"], work["this_run"], cache_dir, device)
    # Anywhere else (a notebook on its own) the method is a run of its own, added to the folder.
    with runs.new_run(output_dir, "notebook") as building:
        if params is not None:  # the params it ran with, as a run of ``run`` keeps them
            config.write_resolved_params(params, building)
        work = compute_method(sequence, conf, cache_dir, device, seed, run_id=runs.run_id(building), **options)
        table = write_results(building, sequence, conf, seed, work["environment"], work["this_run"], cache_dir, device)
    scoring.refresh_view(output_dir)  # the folder's table, derived from its runs
    return table


@functools.cache
def code_digest() -> str:
    """BLAKE2b of the files this process's gvbench_nb ships (code, recipes, tables: a checkout and its wheel
    agree; an editor's backup or a cache file beside them does not count)."""
    import gvbench_nb

    root = Path(gvbench_nb.__file__).parent
    digest = hashlib.blake2b(digest_size=6)
    for path in sorted(p for p in root.rglob("*") if p.suffix in (".py", ".csv", ".json", ".yaml") and p.is_file()):
        digest.update(path.relative_to(root).as_posix().encode() + b"\0" + path.read_bytes())
    return digest.hexdigest()


def write_results(
    run: Path,
    sequence: Sequence,
    conf: dict[str, Any],
    seed: int,
    environment: dict[str, Any],
    this_run: dict[str, Any],
    cache_dir: Path,
    device: str = "auto",
) -> pd.DataFrame:
    """The one way a method's results are written (a run, a notebook, a merge), into a run being
    built: its table from the stores, ``run.json``, then ``pairs.csv``."""
    folder = Path(run) / conf["method"]
    table = pairs_table(sequence, conf, cache_dir, seed)
    atomic_write_json(
        folder / "run.json",
        {
            **result_identity(sequence, conf, seed, device),
            "n_pairs": len(sequence.pairs),
            "pairs": sequence.origin,
            "package_version": __version__,
            "code_digest": code_digest(),
            # Every checkpoint the method loaded: path, git blob id, whether it is the published one.
            "weights": weights.held_weights(image_features.checkpoints_of(conf["extractor"], conf["matcher"])),
            "run_id": runs.run_id(run),
            "cache_dir": str(cache_dir),  # where its matches are (``pair_matching.match_store``)
            "environment": environment,
            "this_run": this_run,
            "finished_at": runs.now(),
        },
    )
    atomic_write_csv(folder / "pairs.csv", table)  # last: its presence marks a finished method
    return table


def run_method_of_params(params: dict[str, Any], sequence: Sequence, method: str, **options: Any) -> pd.DataFrame:
    """``run_method`` with what a loaded params file sets: profile, output and cache folders,
    device, seed and verifier overrides (how the CLI, the notebooks and the analyses run a method)."""
    return run_method(
        sequence,
        method,
        params["profile"],
        Path(params["output_dir"]),
        Path(params["cache_dir"]),
        params["device"],
        params["seed"],
        verifier=params.get("verifier") or None,
        params=params,
        **options,
    )
