"""``--jobs N``: images, then pairs, a run processes at once (``concurrency.job_count``); the flag of
``run`` and of the bench, exported as $GVBENCH_JOBS. A Dask cluster's size is ``--dask-workers``."""

from __future__ import annotations

import argparse
import os

from gvbench_nb.io_utils import whole_number_at_least
from gvbench_nb.runner.concurrency import JOBS_ENV


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
