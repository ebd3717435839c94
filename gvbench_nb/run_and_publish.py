"""``python -m gvbench_nb run``: check the inputs, compute in a stage, execute the stage notebooks
with papermill, then publish the stage whole into the output folder and print the results.
"""

from __future__ import annotations

import argparse
import logging
import os
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

from gvbench_nb.reporting.execute import execute_notebook, kernels_ahead  # light: papermill is imported when used

if TYPE_CHECKING:
    import pandas as pd

    from gvbench_nb.data.sequences import Sequence

log = logging.getLogger(__name__)


def execute_run_notebooks(
    jobs: list[tuple[str, str, dict[str, Any]]], output_dir: Path, compute: Callable[[str], None]
) -> None:
    """Execute 01_sequence at once, each 02_verify once ``compute(method)`` wrote its result (torch
    imported once), 03_evaluate once all are written; errors are raised in job order, and a failed
    computation is left to its notebook (which keeps the traceback), the methods after it not started."""
    from concurrent.futures import Future, ThreadPoolExecutor

    def execute(job: tuple[str, str, dict[str, Any]]) -> None:
        # Lines, not a bar: notebooks overlap each other and the stages' own progress bars.
        source, target, parameters = job
        log.info(f"executing {source} -> {output_dir / target}")
        execute_notebook(source, output_dir / target, parameters)

    def failed(futures: list[Future]) -> bool:
        return any(future.done() and future.exception() is not None for future in futures)

    def finish(futures: list[Future]) -> None:
        for future in futures:  # in job order: the first failing notebook's error is raised
            future.result()

    # Every notebook's kernel is started ahead (``kernels_ahead``), while this process computes.
    with kernels_ahead(len(jobs)), ThreadPoolExecutor(max_workers=max(2, os.cpu_count() or 1)) as pool:
        started: list[Future] = []
        try:
            for job in jobs[:-1]:
                if failed(started):
                    finish(started)  # a notebook failed: raise its error before more work
                method = job[2].get("method")
                if method is not None:
                    try:
                        compute(method)
                    except Exception:
                        finish(started)  # earlier notebooks' errors first
                        execute(job)  # raises this method's error from its notebook
                        continue
                started.append(pool.submit(execute, job))
            if failed(started):
                finish(started)
            started.append(pool.submit(execute, jobs[-1]))
            finish(started)
        finally:
            for future in started:
                future.cancel()


def command_run(args: argparse.Namespace) -> int:
    from gvbench_nb.runner import (
        config,
        distributed,
        image_features,
        input_checks,
        method_runs,
        runs,
        scoring,
        sequence_build,
    )  # fmt: skip

    # Weights, vismatch, the device, the folders and, for a pair file, every image were checked before
    # any work (``check_before_work``, which hands on the params and what it found): nothing half-runs.
    params, damaged = getattr(args, "checked", None) or (run_params_of_args(args), None)
    output_dir = Path(params["output_dir"])
    runs.check_owned(output_dir)  # whose folder it is, before anything is written there
    sequence = sequence_build.prepare_sequence(params)
    if damaged is None:  # a builder's pairs, checked once built (kept in the cache)
        input_checks.check_labels_defined(sequence, params)
        sequence.check_images()
        damaged = input_checks.check_image_contents(sequence, params["cache_dir"], params["allow_damaged_images"])
    if getattr(args, "dask", False) and args.scheduler:  # its workers share the folders this run is to make
        distributed.check_cluster(args.scheduler, params, sequence)
    input_checks.check_writable_folder(params, "output_dir")
    input_checks.check_writable_folder(params, "cache_dir")
    # What the decoder said in the checks before work, kept in the cache now that it exists.
    keys = image_features.image_keys(sequence, params["cache_dir"])
    input_checks.decoder_messages(sequence, keys, Path(params["cache_dir"]))
    announce_run(params, sequence)
    if distributed.wants_scale_out(args):  # shards and Dask skip the notebooks
        distributed.run_from_cli(args, params)
        if not getattr(args, "shard", None):  # a merge, or a Dask run, ends with the folder's table
            print_run_results(output_dir, params["methods"])
        return 0
    # The run is built aside and added to the folder whole; earlier runs are never touched.
    building = runs.start(output_dir, "run")
    try:
        run_params, jobs = stage_notebooks(params, building, args.jobs)

        def compute(method: str) -> None:
            method_runs.run_method_of_params(run_params, sequence, method, jobs=args.jobs)

        execute_run_notebooks(jobs, building, compute)
        config.write_resolved_params(params, building)  # as given: the output folder's own paths
        run = runs.finish(building, **({"damaged_images": damaged} if damaged else {}))
    except Exception:
        log.warning(
            f"the run did not finish: {output_dir} shows what it showed before; this run's partial work and executed "
            f"notebooks are in {building}"
        )
        raise
    doing = "printing its table"
    try:
        print_run_results(run, params["methods"])  # its own table, whatever landed beside it meanwhile
        doing = "writing the folder's results.csv"
        scoring.refresh_view(output_dir)  # the folder's table for people, derived from its runs
        print(folder_line(output_dir, run) or "", end="")
        for line in scoring.left_out(output_dir):
            log.warning(f"not in this table: {line}")
        if leftovers := runs.leftovers(output_dir):
            log.warning(leftovers)
    except Exception as error:
        reason = f"{error.filename or 'a file'}: {error.strerror}" if isinstance(error, OSError) else str(error)
        raise runs.RunsError(
            f"run {run.name} landed in {output_dir}; {doing} failed ({reason}); "
            f"`python -m gvbench_nb results {output_dir}` makes it again"
        ) from error
    return 0


def folder_line(output_dir: Path, run: Path) -> str | None:
    """The line saying which runs the folder's table shows, when they are not only ``run``."""
    from gvbench_nb.runner import runs

    shown = runs.current(output_dir).entries.items()
    others: dict[str, list[str]] = {}
    for label, entry in shown:
        if entry.run != run:
            others.setdefault(entry.run.name, []).append(label)
    if not others:
        return None
    what = "also" if any(entry.run == run for _, entry in shown) else "not this run but"
    listed = "; ".join(f"{', '.join(labels)} of run {name}" for name, labels in others.items())
    return f"{output_dir} shows {what} {listed} (python -m gvbench_nb results {output_dir})\n"


def announce_run(params: dict[str, Any], sequence: Sequence) -> None:
    """A run's first lines, before any work: what it runs, where to and with which feature cache,
    and, when its estimate exceeds ``run_estimate.LONG_RUN_SECONDS``, how long it will take."""
    from gvbench_nb.runner import image_features, run_estimate

    images, contents = len(sequence.images), len(image_features.content_keys(sequence))
    log.info(
        f"{sequence.name}: {len(sequence.pairs)} pairs, {images} images"
        + (f", {contents} distinct contents" if contents != images else "")
        + f", methods {', '.join(params['methods'])}, profile {params['profile']} -> {params['output_dir']} "
        f"(feature cache {params['cache_dir']})"
    )
    note = run_estimate.long_run_note(params, sequence)
    if note:
        log.warning(note)


def stage_notebooks(
    params: dict[str, Any], stage: Path, jobs: int | None
) -> tuple[dict[str, Any], list[tuple[str, str, dict[str, Any]]]]:
    """The params as the stage's notebooks load them (resolved once, the same sequence) and the
    notebooks to execute: (template, executed name, parameters)."""
    from gvbench_nb import notebook
    from gvbench_nb.runner import config

    run_params = {**params, "output_dir": str(stage)}
    common = {"params_file": str(notebook.final_path(config.write_resolved_params(run_params, stage)))}
    notebooks: list[tuple[str, str, dict[str, Any]]] = [("01_sequence.ipynb", "01_sequence.ipynb", common)]
    notebooks += [
        ("02_verify.ipynb", f"02_verify_{m}.ipynb", {**common, "method": m, "jobs": jobs}) for m in params["methods"]
    ]
    notebooks.append(("03_evaluate.ipynb", "03_evaluate.ipynb", {**common, "methods": None}))
    return run_params, notebooks


def print_run_results(folder: Path, methods: list[str]) -> None:
    """The results table of a run (or of the rows an output folder shows) as ``run`` ends, ``methods``
    first in their order, with a note on timers taken from the cache."""
    from gvbench_nb.runner import runs, scoring

    print_results(scoring.evaluate(folder, write=False), methods)
    for line in scoring.left_out(folder):
        log.warning(f"not in this table: {line}")
    log.info(f"results table: {runs.output_folder(folder) / 'results.csv'}")


def print_results(results: pd.DataFrame, methods: list[str]) -> None:
    order = {method: rank for rank, method in enumerate(methods)}
    rank = lambda rows: rows.str.split(" (", regex=False).str[0].map(order).fillna(len(order))
    results = results.sort_values("method", key=rank, kind="stable")
    columns = ["method", "profile", "n_pairs", "n_positives", "ap", "max_recall", "seconds_per_pair", "timers"]
    imported = results["timers"] == "imported"
    shown = results[columns].astype({"seconds_per_pair": object})
    # Scores computed elsewhere have no seconds; the others to 3 decimals, as AP and MR.
    shown["seconds_per_pair"] = ["imported" if i else f"{s:.3f}" for i, s in zip(imported, results["seconds_per_pair"])]
    print(shown.to_string(index=False, float_format=lambda v: f"{v:.3f}"))
    reused = results.loc[~imported & (results["timers"] != "this run"), "method"].tolist()
    if reused:
        log.info(
            f"note: {', '.join(reused)}: images or pairs came from the cache, so their seconds are those of the runs "
            "that computed them (timers column), not this run's"
        )


def run_params_of_args(args: argparse.Namespace) -> dict[str, Any]:
    """The params of a ``run`` command line: its params file with the options applied
    (paths typed on the command line are relative to the current folder)."""
    from gvbench_nb.runner import config

    def absolute(path: str | None, flag: str) -> str | None:
        if path is not None and not path.strip():  # "" would silently mean the params file's folder
            raise config.ParamsError(f"{flag} is empty; give a folder, or leave {flag} out to use the params file's")
        return str(config.real_path(path)) if path else None

    return config.load_params(
        args.params,
        methods=args.methods,
        limit=args.limit,
        profile=args.profile,
        output_dir=absolute(args.output_dir, "--output-dir"),
        image_root=absolute(args.image_root, "--image-root"),
    )
