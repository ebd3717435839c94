"""Scale out: (sequence x method) jobs in shards (extraction, then matching, then a merge), by hand
(``run --shard i/n``, ``--merge``) or on Dask. RANSAC is seeded per pair (``pair_matching.pair_seed``),
so the merged table equals an unsharded run's, timing columns aside."""

from __future__ import annotations

import argparse
import contextlib
import os
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pandas as pd

from gvbench_nb import GVBenchError, __version__
from gvbench_nb import methods as method_registry
from gvbench_nb.data.sequences import Sequence
from gvbench_nb.runner import concurrency, image_features, method_runs, pair_matching, runs, scoring


class ShardError(GVBenchError, RuntimeError):
    """A shard failed, a Dask worker lacks what the shards need, or the merge found pairs no shard has finished."""


# ------------------------------------------------------------------------ shards --
def parse_shard(text: str) -> tuple[int, int]:
    """'i/n' -> (i, n) with 0 <= i < n; the error says what a valid value looks like."""
    try:
        index_text, count_text = text.split("/")
        index, count = int(index_text), int(count_text)
    except ValueError:
        raise ValueError(f"--shard must look like I/N (e.g. 0/4 for the first of four shards), got {text!r}") from None
    if count < 1 or not 0 <= index < count:
        raise ValueError(f"--shard {text}: need N >= 1 and 0 <= I < N (shards are numbered from 0)")
    return index, count


def pair_shard(sequence: Sequence, index: int, count: int) -> Sequence:
    """Shard ``index`` of ``count``: every ``count``-th pair from ``index``, same image root."""
    return Sequence(sequence.name, sequence.image_root, sequence.pairs[index::count])


def extract_shard(
    sequence: Sequence,
    extractor_conf: dict[str, Any],
    cache_dir: str,
    index: int,
    count: int,
    device: str = "auto",
    threads: int | None = None,
) -> dict[str, int]:
    """Phase 1 task: extract image slice ``index::count`` of ``sequence`` into the cache."""
    from gvbench_nb.protocol.features.base import resolve_device  # imports torch

    jobs = concurrency.job_count()
    concurrency.configure_threads(threads, jobs)
    return image_features.extract_features(
        sequence,
        extractor_conf,
        Path(cache_dir),
        resolve_device(device),
        progress=False,
        images=sequence.images[index::count],
        jobs=jobs,
    )


def match_shard(
    sequence: Sequence,
    conf: dict[str, Any],
    cache_dir: str,
    index: int,
    count: int,
    device: str = "auto",
    seed: int = 0,
    threads: int | None = None,
    after: list[Any] | None = None,
) -> dict[str, Any]:
    """Phase 2 task: extract what is missing, match and verify pair shard ``index::count`` (``after``: order only)."""
    if count > 1 and method_registry.is_dense(conf) and pair_matching.dense_merge_options(conf["matcher"]) is not None:
        raise ValueError(
            f"method {conf['method']!r} merges its dense keypoints across all pairs of the sequence, "
            "so its pairs cannot be matched in shards; run it with one matching shard"
        )
    shard = pair_shard(sequence, index, count)
    work = method_runs.compute_method(shard, conf, Path(cache_dir), device, seed, progress=False, threads=threads)
    return {"shard": f"{index}/{count}", **work["this_run"]}


# ------------------------------------------------------------------------- merge --
def merge_method(
    sequence: Sequence,
    conf: dict[str, Any],
    cache_dir: Path,
    output_dir: Path,
    seed: int = 0,
    device: str = "auto",
    shards: list[dict[str, Any]] | None = None,
    cached: dict[str, dict[str, int]] | None = None,
) -> pd.DataFrame:
    """Phase 3: the full sequence's ``pairs.csv`` and ``run.json`` from the shared stores; ``cached``
    (``cached_work`` before the shards ran) gives ``run.json`` the counts its timers are told from."""
    from gvbench_nb.protocol.features.base import resolve_device  # imports torch

    missing = missing_pairs(sequence, conf, cache_dir, seed)
    if missing:
        first = sequence.pairs.index(missing[0])
        store = pair_matching.match_store(cache_dir, conf, pair_matching.pair_keys(sequence, seed))
        raise ShardError(
            f"cannot merge {conf['method']} on {sequence.name}: {len(missing)} of {len(sequence.pairs)} pairs have "
            f"no result in {store.folder} (first: pair {first}, "
            f"{missing[0].query} {missing[0].reference}). Run the shards that are missing (or all of them again: "
            "finished pairs are skipped), then merge."
        )
    environment = concurrency.environment_info(resolve_device(device))
    sharding = {"sharded": True, "n_shards": len(shards or []), "shards": shards or [], **(cached or {})}
    return method_runs.write_results(output_dir, sequence, conf, seed, environment, sharding, cache_dir)


def missing_pairs(sequence: Sequence, conf: dict[str, Any], cache_dir: Path, seed: int) -> list[Any]:
    """The pairs of ``sequence`` that the method's match store holds no result for."""
    keys = pair_matching.pair_keys(sequence, seed)
    store = pair_matching.match_store(cache_dir, conf, keys)
    store.refresh()
    missing = [pair for pair, key in keys.items() if key not in store]
    store.close()
    return missing


def cached_work(sequence: Sequence, conf: dict[str, Any], cache_dir: Path, seed: int) -> dict[str, dict[str, int]]:
    """The images and pairs of a method that the caches hold before a run, counted as ``compute_method``
    counts them; once the run's shards have done the rest, the counts of its whole work (``scoring.timers_source``)."""
    images = cached_images = 0
    if conf["extractor"]:
        store = image_features.feature_store(cache_dir, conf["extractor"])
        store.refresh()
        keys = image_features.content_keys(sequence)
        images, cached_images = len(keys), sum(key in store for key in keys)
        store.close()
    pairs = len(sequence.pairs)
    cached_pairs = pairs - len(missing_pairs(sequence, conf, cache_dir, seed))
    return {
        "extraction": {"images": images, "cached": cached_images, "extracted": images - cached_images},
        "matching": {"pairs": pairs, "cached": cached_pairs, "matched": pairs - cached_pairs},
    }


def _require_weights(params: dict[str, Any]) -> None:
    for method in params["methods"]:
        method_registry.require(method, params["profile"])


# --------------------------------------------------------------- one machine ----
def run_shard(
    params: dict[str, Any], index: int, count: int, threads: int | None = None, progress: bool = True
) -> list[dict[str, Any]]:
    """Shard ``index`` of ``count`` of every method of a params file, here (``run --shard i/n``): its work
    goes into the shared stores, and the folder gets a run saying what it did (``--merge`` makes the table)."""
    from gvbench_nb.runner.sequence_build import prepare_sequence

    _require_weights(params)
    sequence = prepare_sequence(params)
    building = runs.start(params["output_dir"], "shard")
    done = []
    for method in params["methods"]:
        conf = method_registry.resolve_method(method, params["profile"], params.get("verifier"))
        if conf["extractor"]:
            extract_shard(sequence, conf["extractor"], params["cache_dir"], index, count, params["device"], threads)
        result = match_shard(
            sequence, conf, params["cache_dir"], index, count, params["device"], params["seed"], threads,
        )  # fmt: skip
        if progress:
            print(
                f"{sequence.name} {method}: shard {index}/{count} done "
                f"({result['matching']['matched']} pairs matched, "
                f"{result['extraction']['extracted']} images extracted)"
            )
        done.append({"method": method, **result})
    runs.finish(building, shard=f"{index}/{count}", work=done)
    return done


def merge_runs(
    params: dict[str, Any],
    shards: dict[str, list[dict[str, Any]]] | None = None,
    cached: dict[str, dict[str, dict[str, int]]] | None = None,
    door: str = "merge",
) -> pd.DataFrame:
    """Merge every method of a params file into a new run, then the folder's table (``run --merge``;
    ``cached`` by method: ``merge_method``)."""
    from gvbench_nb.runner.sequence_build import prepare_sequence

    sequence = prepare_sequence(params)
    output_dir, cache_dir = Path(params["output_dir"]), Path(params["cache_dir"])
    with runs.new_run(output_dir, door) as building:
        for method in params["methods"]:
            conf = method_registry.resolve_method(method, params["profile"], params.get("verifier"))
            merge_method(
                sequence, conf, cache_dir, building, params["seed"], params["device"], (shards or {}).get(method),
                (cached or {}).get(method),
            )  # fmt: skip
    return scoring.refresh_view(output_dir)


# -------------------------------------------------------------------------- Dask --
@contextlib.contextmanager
def dask_client(scheduler: str | None = None, n_workers: int | None = None, processes: bool = True) -> Iterator[Any]:
    """A client of ``scheduler`` (tcp://host:8786), else of a new LocalCluster of single-threaded workers."""
    from distributed import Client, LocalCluster

    if scheduler:
        with Client(scheduler) as client:
            yield client
        return
    workers = n_workers or os.cpu_count() or 1
    with (
        LocalCluster(n_workers=workers, threads_per_worker=1, processes=processes, dashboard_address=None) as cluster,
        Client(cluster) as client,
    ):
        yield client


def run_sharded(
    params: dict[str, Any],
    n_shards: int,
    scheduler: str | None = None,
    n_workers: int | None = None,
    processes: bool = True,
    threads: int | None = None,
    progress: bool = True,
) -> pd.DataFrame:
    """One params file's methods in ``n_shards`` shards on one Dask cluster, all submitted at once;
    returns its results table."""
    from distributed import wait
    from tqdm import tqdm

    from gvbench_nb.runner.sequence_build import prepare_sequence

    if n_shards < 1:
        raise ValueError(f"n_shards must be at least 1, got {n_shards}")
    _require_weights(params)
    sequence = prepare_sequence(params)
    if threads is None and scheduler is None:
        # Each core used by one task's threads: more makes torch spin-wait (2-5x slower).
        threads = max(1, (os.cpu_count() or 1) // (n_workers or os.cpu_count() or 1))
    with dask_client(scheduler, n_workers, processes) as client:
        check_workers(client, params, sequence)
        runs.claim(params["output_dir"])  # the workers write match stores there before the run is added
        cached = {
            method: cached_work(
                sequence, method_registry.resolve_method(method, params["profile"], params.get("verifier")),
                Path(params["cache_dir"]), params["seed"],
            )
            for method in params["methods"]
        }  # fmt: skip
        matching = _submit_shards(client, params, sequence, n_shards, threads)
        bar = tqdm(total=sum(len(f) for f in matching.values()), desc="shards", unit="shard", disable=not progress)
        shards: dict[str, list[dict[str, Any]]] = {}
        for method, futures in matching.items():
            wait(futures)
            shards[method] = []
            for i, future in enumerate(futures):
                try:
                    shards[method].append(future.result())
                except Exception as error:
                    raise ShardError(
                        f"shard {i}/{n_shards} of {method} on {sequence.name} failed: {type(error).__name__}: {error}"
                    ) from error
                bar.update()
        bar.close()
        return merge_runs(params, shards, cached, door="dask")


def package_code() -> str:
    """This process's gvbench_nb: its version and the digest of the files it ships (``method_runs.code_digest``)."""
    return f"{__version__} (code {method_runs.code_digest()})"


def shared_view(image: str, marks: dict[str, str]) -> dict[str, str]:
    """What a Dask worker must see as the submitting process does: the package, the bytes of an image
    of the sequence, and the files the submitting process placed in the shared folders (``marks``)."""
    view = {"gvbench_nb": package_code()}
    try:
        view["image root"] = image_features.content_key(image)
    except GVBenchError:
        view["image root"] = "missing"
    return view | {name: "present" if Path(mark).is_file() else "missing" for name, mark in marks.items()}


def check_cluster(scheduler: str, params: dict[str, Any], sequence: Sequence) -> None:
    """``check_workers`` on the cluster of ``scheduler`` (``run --dask --scheduler``, before any folder is made)."""
    with dask_client(scheduler) as client:
        check_workers(client, params, sequence)


def check_workers(client: Any, params: dict[str, Any], sequence: Sequence) -> None:
    """Refuse, in one sentence and before any work, a Dask cluster without workers, or a worker
    that sees another package or other images or folders than this process (``shared_view``)."""
    image = str(Path(sequence.image_root) / sequence.images[0])
    folders = {"cache folder": Path(params["cache_dir"]), "output folder": Path(params["output_dir"])}
    with contextlib.ExitStack() as placed:
        marks = {}
        for name, folder in folders.items():  # in the folder, or where it will be made
            existing = next(p for p in (folder, *folder.parents) if p.is_dir())
            marks[name] = placed.enter_context(tempfile.NamedTemporaryFile(dir=existing, prefix=".write-check-")).name
        here = shared_view(image, marks)
        views = client.run(shared_view, image, marks, on_error="return")
    if not views:
        address = client.scheduler.address
        raise ShardError(
            f"the Dask scheduler {address} has no workers: start them (dask worker {address}), then run again"
        )
    for worker, view in sorted(views.items()):
        if isinstance(view, BaseException):
            differences = [f"cannot run gvbench_nb's check of the workers ({type(view).__name__}: {view})"]
        else:
            seen = {key: view.get(key, "missing") for key in here}  # a worker of another version may see less
            differences = [
                _difference(key, seen[key], here[key], image, folders, marks) for key in here if seen[key] != here[key]
            ]
        if differences:
            raise ShardError(
                f"Dask worker {worker} {' and '.join(differences)}: every worker needs this package at the same "
                "version and code, and the image root, cache folder and output folder at the same paths on a "
                "shared filesystem (docs/speed.md)"
            )


def _difference(key: str, there: str, here: str, image: str, folders: dict[str, Path], marks: dict[str, str]) -> str:
    if key == "gvbench_nb":
        return f"runs gvbench_nb {there} where this process runs {here}"
    if key == "image root":
        return f"does not see the image {image}" if there == "missing" else f"reads other bytes in the image {image}"
    written = Path(marks[key]).parent
    return f"does not see the {key} {folders[key]} as this process does (a file written in {written} is missing there)"


def _submit_shards(
    client: Any, params: dict[str, Any], sequence: Sequence, n_shards: int, threads: int | None
) -> dict[str, list[Any]]:
    """Submit extraction shards (once per extractor) and matching shards after them, by method."""
    extraction: dict[str, list[Any]] = {}
    matching: dict[str, list[Any]] = {}
    cache_dir, device = params["cache_dir"], params["device"]
    for method in params["methods"]:
        conf = method_registry.resolve_method(method, params["profile"], params.get("verifier"))
        after: list[Any] = []
        if conf["extractor"]:
            extractor = conf["extractor"]
            key = method_registry.conf_hash(extractor)
            if key not in extraction:  # methods sharing an extractor share its shards
                name = f"extract-{sequence.name}-{extractor['name']}-{key}"
                extraction[key] = [
                    client.submit(
                        extract_shard, sequence, extractor, cache_dir, i, n_shards, device, threads,
                        pure=False, key=f"{name}-{i}of{n_shards}",
                    )
                    for i in range(n_shards)
                ]  # fmt: skip
            after = extraction[key]
        matching[method] = [
            client.submit(
                match_shard, sequence, conf, cache_dir, i, n_shards, device, params["seed"], threads,
                after, pure=False, key=f"match-{sequence.name}-{method}-{i}of{n_shards}",
            )
            for i in range(n_shards)
        ]  # fmt: skip
    return matching


# -------------------------------------------------------------------------- CLI --
def add_run_arguments(run: argparse.ArgumentParser) -> None:
    """The ``run`` command's --jobs and scale-out options (cli.py calls this on its ``run`` parser)."""
    from gvbench_nb.runner.concurrency import add_jobs_argument

    add_jobs_argument(
        run,
        None,
        "images, then pairs, processed at once, each on its own threads (default: $GVBENCH_JOBS, else every "
        "core this process may use); each image's and pair's timer is its job's own time",
    )
    group = run.add_argument_group("scale-out (no notebooks; results as `run` writes them)")
    group.add_argument("--shard", metavar="I/N", help="run only shard I of N (0-based) here; then --merge")
    group.add_argument("--merge", action="store_true", help="merge finished shards into one run (pairs.csv, run.json)")
    group.add_argument("--dask", action="store_true", help="run all shards on Dask and merge")
    group.add_argument("--scheduler", metavar="ADDR", help="Dask scheduler address (default: a LocalCluster here)")
    group.add_argument("--shards", type=int, help="number of shards with --dask (default: 2 per Dask worker)")
    group.add_argument(
        "--dask-workers",
        type=int,
        metavar="N",
        help="with --dask: the LocalCluster's worker processes (default: one per core)",
    )


def wants_scale_out(args: argparse.Namespace) -> bool:
    return bool(getattr(args, "shard", None) or getattr(args, "merge", False) or getattr(args, "dask", False))


def check_scale_out_options(args: argparse.Namespace) -> None:
    """One of --shard, --merge and --dask at most, a well-formed --shard; ``ValueError`` names the options."""
    chosen = [flag for flag, on in (("--shard", args.shard), ("--merge", args.merge), ("--dask", args.dask)) if on]
    if len(chosen) > 1:
        raise ValueError(f"choose one of --shard, --merge and --dask, not {' and '.join(chosen)}")
    if args.shard:
        parse_shard(args.shard)


def run_from_cli(args: argparse.Namespace, params: dict[str, Any]) -> int:
    """``run --shard I/N`` | ``run --merge`` | ``run --dask [--scheduler ADDR] [--shards N]``."""
    check_scale_out_options(args)
    if args.shard:
        index, count = parse_shard(args.shard)
        run_shard(params, index, count)
        print(
            f"shard {index}/{count} finished; when all {count} are: python -m gvbench_nb run "
            f"{params['params_file']} --merge (with the same --methods/--limit/--profile)"
        )
        return 0
    dask_workers = args.dask_workers or os.cpu_count() or 1
    if args.merge:
        merge_runs(params)
    else:
        n_shards = args.shards or 2 * dask_workers
        run_sharded(params, n_shards, args.scheduler, n_workers=None if args.scheduler else dask_workers)
    return 0
