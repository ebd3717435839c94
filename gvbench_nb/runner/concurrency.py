"""How many threads and jobs a run uses (``--jobs N``: images, then pairs, at once, exported as
$GVBENCH_JOBS; a Dask cluster's size is ``--dask-workers``), the prefetching executor, and the machine
it ran on."""

from __future__ import annotations

import argparse
import os
import platform
import sys
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from typing import TYPE_CHECKING, Any, TypeVar

import cv2
import numpy as np

from gvbench_nb.io_utils import whole_number_at_least

if TYPE_CHECKING:
    import torch


# torch and the model modules (extractors, matchers) are imported by the functions that
# run models: a notebook or command that only reads results never pays for them.
T = TypeVar("T")
R = TypeVar("R")


def available_cores() -> int:
    """The cores this process may run on: its CPU affinity (what a container, taskset or a batch
    scheduler grants), else the machine's count."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # macOS and Windows have no affinity call
        return os.cpu_count() or 1


THREADS_ENV = "GVBENCH_THREADS"  # threads a job: OpenCV's


def configure_threads(n_threads: int | None = None, jobs: int = 1) -> int:
    """Set OpenCV's thread count: ``n_threads``, else $GVBENCH_THREADS, else the available cores shared
    by ``jobs`` (more threads than cores wait on each other). torch and numpy's BLAS run on one thread
    a job: their sums round differently on each thread count, OpenCV's steps that a run uses do not."""
    from threadpoolctl import threadpool_limits

    from gvbench_nb.protocol.features.base import torch_on_one_thread

    n = n_threads or threads_of_environment() or max(1, available_cores() // max(jobs, 1))
    torch_on_one_thread()
    cv2.setNumThreads(n)
    threadpool_limits(1)  # numpy's BLAS (the OpenCV-rule L2 products); kept for the process
    return n


def threads_of_environment() -> int | None:
    """$GVBENCH_THREADS as a whole number of at least 1, or None when unset."""
    text = os.environ.get(THREADS_ENV) or ""
    if text and not (text.isdigit() and int(text) >= 1):
        raise ValueError(
            f"the environment variable {THREADS_ENV} (threads a job) must be a whole number of at least 1, "
            f"got {text!r}; fix or unset it"
        )
    return int(text) if text else None


JOBS_ENV = "GVBENCH_JOBS"  # the run's parallelism, as `run --jobs` and the bench's `--jobs` set it


def job_count(jobs: int | None = None) -> int:
    """Images, then pairs, processed at once: ``jobs``, else $GVBENCH_JOBS, else every available core.
    Each item's timer is its own wall time on its job's threads; scores are the same either way."""
    text = os.environ.get(JOBS_ENV) or ""
    try:
        n = jobs if jobs is not None else int(text) if text else available_cores()
    except ValueError:
        n = 0
    if n < 1:
        given = n if jobs is not None else repr(text)
        raise ValueError(f"jobs must be a whole number of at least 1, got {given} (--jobs or ${JOBS_ENV})")
    return n


def jobs_value(text: str) -> int | None:
    """argparse type of --jobs: a whole number of at least 1; "" (no flag, no $GVBENCH_JOBS) is None."""
    if text == "":
        return None
    return whole_number_at_least(text, 1, f"a whole number of at least 1 (--jobs or ${JOBS_ENV})")


class ExportJobs(argparse.Action):
    """Keep --jobs and export it as $GVBENCH_JOBS, which the processes this one starts (a
    Dask cluster's workers, a shard's) read."""

    def __call__(self, parser, namespace, values, option_string=None):
        os.environ[JOBS_ENV] = str(values)
        setattr(namespace, self.dest, values)


def add_jobs_argument(
    parser: argparse.ArgumentParser | argparse._ArgumentGroup, default: int | None, help: str
) -> None:
    """``--jobs N``. Without ``default``, $GVBENCH_JOBS is the default (checked as the flag is);
    the default stays a string so that argparse passes it through ``jobs_value`` too."""
    fallback = str(default) if default is not None else os.environ.get(JOBS_ENV, "")
    parser.add_argument(
        "--jobs", type=jobs_value, default=fallback, action=ExportJobs, metavar="N", dest="jobs", help=help
    )


def prefetch(
    items: Iterable[T], load: Callable[[T], R], depth: int = 4, jobs: int = 2
) -> Iterator[tuple[T, R | BaseException]]:
    """Yield (item, load(item)) in order while the next ``depth`` loads run in threads; a failed
    load is yielded as its exception, for the caller to raise with context."""
    iterator = iter(items)
    pending: list[tuple[T, Future[R]]] = []
    with ThreadPoolExecutor(max_workers=jobs) as pool:
        for item in iterator:
            pending.append((item, pool.submit(load, item)))
            if len(pending) >= depth:
                break
        while pending:
            item, future = pending.pop(0)
            try:
                result: R | BaseException = future.result()
            except Exception as error:  # surfaced in order by the caller
                result = error
            next_item = next(iterator, None)
            if next_item is not None:
                pending.append((next_item, pool.submit(load, next_item)))
            yield item, result


def cpu_name() -> str:
    """The CPU model (for timings to say what they were measured on)."""
    try:
        with open("/proc/cpuinfo", encoding="utf-8") as handle:
            for line in handle:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def _version(module: str) -> str:
    """A module's ``__version__``, without importing it when it is not loaded yet (importing
    kornia only to read its version takes longer than a small run's work)."""
    if module in sys.modules:
        return sys.modules[module].__version__
    from importlib.metadata import version

    return version(module)


def environment_info(device: torch.device) -> dict[str, Any]:
    import torch

    return {
        "device": str(device),
        "device_name": torch.cuda.get_device_name(device) if device.type == "cuda" else cpu_name(),
        "cpu_count": os.cpu_count(),
        "torch": torch.__version__,
        "kornia": _version("kornia"),
        "opencv": cv2.__version__,
        "numpy": np.__version__,
        "python": platform.python_version(),
        "platform": platform.platform(),
    }
