"""Shared fixtures: where the real data and the reference layouts are.

The real data is found through the package's data folder (``$GVBENCH_DATA``, else the
per-user cache): tests that need it skip with the ``data fetch`` command that fills it.
``make test`` runs that command first, from ../shared/data when that folder exists.
"""

from __future__ import annotations

import os
import sys
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

PROJECT_ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(PROJECT_ROOT / "benchmarks"))  # the benchmark scripts, imported by their tests

# The tests that read or write the session's outputs/sample (``$GVBENCH_OUTPUTS``, below: the notebooks'
# default params, and runs of params/sample.yaml, which renders its images there) run one at a
# time under pytest-xdist (`make test` runs a worker a core): each holds a lock shared by every
# worker of this session while it runs. (xdist's own `--dist loadgroup` cannot do it: with
# pytest 9 it drops the groups silently.)
SHARED_OUTPUTS = "shared_outputs"
# Under xdist the notebooks also go to one worker, as one unit, in their order (the scheduler
# below): a second worker would only wait on their lock, and it runs the other tests meanwhile.
NOTEBOOKS_UNIT = "notebooks"


# The longest tests of `make test` (pytest --durations on the 2-core machine). disk-lg's real-pairs
# test is not among them: it comes later and finds DISK's features in the cache disk-nn's filled.
LONGEST = (
    "test_available_methods_score_true_pairs_above_far_false_pairs[disk-nn]",
    "test_per_pair_pipeline_and_ours_give_identical_scores[disk-lg]",
    "test_available_methods_score_true_pairs_above_far_false_pairs[aliked-nn]",
    "test_available_methods_score_true_pairs_above_far_false_pairs[aliked-lg]",
    "test_prepared_matches_equal_kornia_bit_for_bit",
)


# The user's folders stay untouched: runs whose params name no cache_dir use $GVBENCH_CACHE, and
# the repository's outputs/ (the shipped params' and the notebooks' default folders, which nbmake
# runs) is $GVBENCH_OUTPUTS, both in a folder of this test session's (its xdist workers and notebook
# kernels inherit the controller's). Each test then gets its own cache (``own_feature_cache``),
# kept beside its tmp_path/out as the tests read it.
SESSION_FOLDER = "GVBENCH_TESTS_SESSION_FOLDER"
made_session_folder: list[str] = []  # by this process, which removes it at the end
OUTPUTS_BEFORE = pytest.StashKey[dict[str, int]]()


def pytest_configure(config: pytest.Config) -> None:
    if not os.environ.get(SESSION_FOLDER):
        os.environ[SESSION_FOLDER] = tempfile.mkdtemp(prefix="gvbench-nb-tests-")
        made_session_folder.append(os.environ[SESSION_FOLDER])
    os.environ["GVBENCH_CACHE"] = os.path.join(os.environ[SESSION_FOLDER], "cache")
    os.environ["GVBENCH_OUTPUTS"] = os.path.join(os.environ[SESSION_FOLDER], "outputs")
    if os.environ.get("PYTEST_XDIST_WORKER"):
        # One torch/OpenCV thread a worker: two workers on two cores, each spinning two threads,
        # would wait on each other. Runs (and their notebook kernels) read GVBENCH_THREADS and GVBENCH_JOBS.
        os.environ.setdefault("GVBENCH_THREADS", "1")
        os.environ.setdefault("GVBENCH_JOBS", "1")  # and one job a run: the workers are the cores' jobs
        os.environ.setdefault("OMP_NUM_THREADS", "1")
        import cv2
        import torch

        torch.set_num_threads(1)
        cv2.setNumThreads(1)


def repository_outputs() -> dict[str, int]:
    """Each file under the repository's outputs/ with its modification time (ns)."""
    return {str(path): path.stat().st_mtime_ns for path in (PROJECT_ROOT / "outputs").rglob("*") if path.is_file()}


def pytest_sessionstart(session: pytest.Session) -> None:
    session.config.stash[OUTPUTS_BEFORE] = repository_outputs()


def pytest_sessionfinish(session: pytest.Session, exitstatus: int) -> None:
    """A session that wrote under the repository's outputs/ fails, naming what it wrote."""
    before, after = session.config.stash[OUTPUTS_BEFORE], repository_outputs()
    written = sorted(path for path, mtime in after.items() if before.get(path) != mtime)
    if written and not os.environ.get("PYTEST_XDIST_WORKER"):
        print(f"\nthe tests wrote {len(written)} file(s) under {PROJECT_ROOT / 'outputs'}, such as {written[0]}")
        session.exitstatus = pytest.ExitCode.TESTS_FAILED


def pytest_unconfigure(config: pytest.Config) -> None:
    import shutil

    for folder in made_session_folder:
        shutil.rmtree(folder, ignore_errors=True)


@pytest.fixture(autouse=True)
def own_feature_cache(request: pytest.FixtureRequest, monkeypatch: pytest.MonkeyPatch) -> None:
    """The default feature cache of a test is ``tmp_path/cache``."""
    if "tmp_path" in request.fixturenames:
        monkeypatch.setenv("GVBENCH_CACHE", str(request.getfixturevalue("tmp_path") / "cache"))


def is_notebook(nodeid: str) -> bool:
    return nodeid.split("::", 1)[0].endswith(".ipynb")


@pytest.hookimpl(optionalhook=True)  # pytest -p no:xdist
def pytest_xdist_make_scheduler(config: pytest.Config, log: Any) -> Any:
    """xdist's load scheduling, one test a unit, except the notebooks: one unit, so one worker
    runs them in order while the others take the tests one by one as they free up."""
    if config.getoption("dist") != "load":
        return None  # a distribution the user chose
    from xdist.scheduler import LoadScopeScheduling

    class NotebooksAsOneUnit(LoadScopeScheduling):
        def _split_scope(self, nodeid: str) -> str:
            return NOTEBOOKS_UNIT if is_notebook(nodeid) else nodeid

    return NotebooksAsOneUnit(config, log)


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    for item in items:
        if item.path.suffix == ".ipynb":  # nbmake runs each notebook with its default params
            item.add_marker(pytest.mark.shared_outputs)
    if os.environ.get("PYTEST_XDIST_WORKER"):
        # Long work first, so that no worker is left with it while the others idle: the notebooks
        # (one unit, above), the few tests that run learned models on whole sequences (minutes
        # each, `--durations`), the other tests of the shared outputs, then the slow tests; order
        # within each kept.
        def rank(item: pytest.Item) -> int:
            if is_notebook(item.nodeid):
                return 0
            if any(name in item.nodeid for name in LONGEST):
                return 1
            if item.get_closest_marker(SHARED_OUTPUTS) is not None:
                return 2
            return 3 if item.get_closest_marker("slow") is not None else 4

        items.sort(key=rank)


@pytest.hookimpl(wrapper=True)
def pytest_runtest_protocol(item: pytest.Item, nextitem: pytest.Item | None) -> Iterator[None]:
    if item.get_closest_marker(SHARED_OUTPUTS) is None:
        return (yield)
    from filelock import FileLock

    with FileLock(os.path.join(os.environ[SESSION_FOLDER], "outputs.lock")):  # setup, call and teardown of the item
        return (yield)


REAL_DATASETS = ("gvbench-lists", "gardens_point")


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """The data folder, holding every file of gardens_point/ and gvbench_gt/ (sizes checked)."""
    from gvbench_nb.data import fetch as data

    root = data.data_dir()
    datasets, _ = data.load_manifest()
    incomplete = [name for name in REAL_DATASETS if data.presence(datasets[name], root)[0] != len(datasets[name].files)]
    if incomplete:
        pytest.skip(
            f"real data not found in {root} ({', '.join(incomplete)}): run "
            f"`python -m gvbench_nb data fetch {' '.join(REAL_DATASETS)}` (offline: add --mirror DIR)"
        )
    return root


@pytest.fixture(scope="session")
def reference_dir() -> Path:
    """``$GVBENCH_REFERENCE`` or ``<repo>/../shared/reference`` (holding ``layouts/``)."""
    env = os.environ.get("GVBENCH_REFERENCE")
    found = Path(env) if env and Path(env).is_dir() else PROJECT_ROOT.parent / "shared" / "reference"
    if not (found / "layouts").is_dir():
        pytest.skip("reference layouts not found: set GVBENCH_REFERENCE to the folder holding layouts/")
    return found


@pytest.fixture
def root(tmp_path) -> Path:
    """Four small photographs under ``tmp_path/images`` (``helpers.write_root``)."""
    from helpers import write_root

    return write_root(tmp_path / "images")


@pytest.fixture
def empty_hub(tmp_path, monkeypatch) -> Path:
    """Point the torch hub cache at an empty folder: no checkpoint is present.
    Yields the checkpoints folder a missing file should be put in."""
    import torch

    old = torch.hub.get_dir()
    torch.hub.set_dir(str(tmp_path / "hub"))
    monkeypatch.setenv("TORCH_HOME", str(tmp_path / "hub"))
    yield tmp_path / "hub" / "checkpoints"
    torch.hub.set_dir(old)
