"""Sharded runs (by hand and through Dask) merge into exactly the unsharded result; how many jobs
a run does at once, and on how many threads each."""

import contextlib
import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import cv2
import pandas as pd
import pytest
import torch
import yaml

from gvbench_nb import __version__, methods
from gvbench_nb.data.sequences import Pair, Sequence, write_pairs
from gvbench_nb.runner import (
    concurrency,
    config,
    distributed,
    image_features,
    method_outputs,
    method_runs,
    scoring,
    sequence_build,
)

METHOD, PROFILE = "sift-nn", "repository"


def twelve_pairs() -> list[Pair]:
    """Three day queries, each with two true neighbouring frames and two false ones (12 pairs).
    Day frames: COLMAP SIFT finds hardly any night-to-day matches at 512 px, so no inliers."""
    return [
        Pair(f"day_right/Image{q:03d}.jpg", f"day_right/Image{r:03d}.jpg", label)
        for q in (30, 90, 150)
        for r, label in ((q + 1, 1), (q + 2, 1), ((q + 50) % 200, 0), ((q + 100) % 200, 0))
    ]


def make_params(shared_data: Path, folder: Path) -> dict:
    """A params file of its own (own output and cache folders) over the same pair file."""
    folder.mkdir(parents=True, exist_ok=True)
    pairs = folder.parent / "pairs.txt"
    if not pairs.is_file():
        write_pairs(pairs, twelve_pairs())
    params = {"sequence": "gp_shards", "pairs": str(pairs), "image_root": str(shared_data / "gardens_point")}
    params |= {"methods": [METHOD], "profile": PROFILE, "output_dir": str(folder / "out")}
    (folder / "params.yaml").write_text(yaml.safe_dump(params | {"cache_dir": str(folder / "cache")}))
    return config.load_params(folder / "params.yaml")


def without_timings(table: pd.DataFrame) -> pd.DataFrame:
    return table[[c for c in table.columns if not c.endswith("_seconds")]]


@pytest.fixture(scope="module")
def unsharded(shared_data, tmp_path_factory) -> pd.DataFrame:
    params = make_params(shared_data, tmp_path_factory.mktemp("runs") / "unsharded")
    method_runs.run_method_of_params(params, sequence_build.prepare_sequence(params), METHOD, progress=False)
    return scoring.load_pairs_table(Path(params["output_dir"]), METHOD)


@pytest.mark.slow
@pytest.mark.real_data
def test_shards_run_by_hand_then_merged_equal_the_unsharded_run(shared_data, unsharded, tmp_path):
    params = make_params(shared_data, tmp_path / "sharded")
    for index in (2, 0, 1):  # any order
        distributed.run_shard(params, index, 3, threads=1, progress=False)
    results = distributed.merge_runs(params)
    merged = scoring.load_pairs_table(Path(params["output_dir"]), METHOD)
    assert len(merged) == 12 and merged["num_inliers"].max() > 0
    pd.testing.assert_frame_equal(without_timings(merged), without_timings(unsharded))
    assert results["n_pairs"].tolist() == [12]
    run = pd.read_json(method_outputs.method_dir(Path(params["output_dir"]), METHOD) / "run.json", typ="series")
    assert run["n_pairs"] == 12 and run["this_run"]["sharded"]


@pytest.mark.slow
@pytest.mark.real_data
def test_dask_local_cluster_run_equals_the_unsharded_run(shared_data, unsharded, tmp_path):
    params = make_params(shared_data, tmp_path / "dask")
    results = distributed.run_sharded(params, n_shards=3, n_workers=2, processes=False, threads=1, progress=False)
    merged = scoring.load_pairs_table(Path(params["output_dir"]), METHOD)
    pd.testing.assert_frame_equal(without_timings(merged), without_timings(unsharded))
    assert results.set_index("method").loc[METHOD, "ap"] == pytest.approx(
        scoring.evaluate(Path(params["output_dir"]), [METHOD], write=False)["ap"].iat[0]
    )
    run = pd.read_json(method_outputs.method_dir(Path(params["output_dir"]), METHOD) / "run.json", typ="series")
    assert [s["shard"] for s in run["this_run"]["shards"]] == ["0/3", "1/3", "2/3"]
    # Every image was extracted exactly once across the extraction shards.
    store = image_features.feature_store(
        Path(params["cache_dir"]), methods.resolve_method(METHOD, PROFILE)["extractor"]
    )
    assert len(store) == len(sequence_build.prepare_sequence(params).images)


@pytest.mark.real_data
def test_merge_with_a_missing_shard_names_the_missing_pairs(shared_data, tmp_path):
    params = make_params(shared_data, tmp_path / "partial")
    distributed.run_shard(params, 0, 3, threads=1, progress=False)
    with pytest.raises(distributed.ShardError, match=r"8 of 12 pairs have no result.*first: pair 1, "):
        distributed.merge_runs(params)
    assert scoring.methods_with_results(Path(params["output_dir"])) == []


@pytest.mark.reliability
def test_a_dask_cluster_without_workers_is_refused_in_one_sentence_before_any_folder(root, tmp_path):
    from distributed import Client, LocalCluster

    sequence = Sequence("s", root, [Pair("query/a.png", "reference/a.png", 1)])
    params = {"cache_dir": str(tmp_path / "run" / "cache"), "output_dir": str(tmp_path / "run" / "out")}
    with (
        LocalCluster(n_workers=0, processes=False, dashboard_address=None) as cluster,
        Client(cluster) as client,
        pytest.raises(distributed.ShardError) as refused,
    ):
        distributed.check_workers(client, params, sequence)
    assert str(refused.value) == (
        f"the Dask scheduler {cluster.scheduler_address} has no workers: start them "
        f"(dask worker {cluster.scheduler_address}), then run again"
    )
    assert sorted(p.name for p in tmp_path.iterdir()) == ["images"]  # no folder made, no mark left


def test_pair_shards_partition_the_pairs():
    sequence = Sequence("s", Path("/images"), twelve_pairs())
    shards = [distributed.pair_shard(sequence, i, 5) for i in range(5)]
    assert sorted((p for s in shards for p in s.pairs), key=sequence.pairs.index) == sequence.pairs


@pytest.mark.parametrize("text", ["3/3", "-1/2", "1", "a/b", "0/0"])
def test_parse_shard_reads_index_and_count_and_rejects_bad_values(text):
    assert distributed.parse_shard("2/5") == (2, 5)
    with pytest.raises(ValueError, match="shard"):
        distributed.parse_shard(text)


def test_job_count_comes_from_the_argument_then_gvbench_jobs(monkeypatch):
    monkeypatch.delenv("GVBENCH_JOBS", raising=False)
    assert concurrency.job_count() == concurrency.available_cores() == len(os.sched_getaffinity(0))
    monkeypatch.setenv("GVBENCH_JOBS", "3")
    assert concurrency.job_count() == 3 and concurrency.job_count(2) == 2
    with pytest.raises(ValueError, match=r"--jobs or \$GVBENCH_JOBS"):
        concurrency.job_count(0)
    monkeypatch.setenv("GVBENCH_JOBS", "two")
    with pytest.raises(ValueError, match=r"got 'two' \(--jobs or \$GVBENCH_JOBS\)"):
        concurrency.job_count()


def test_opencv_threads_a_job_share_the_cores_between_the_jobs_and_torch_and_blas_run_on_one(monkeypatch):
    from threadpoolctl import threadpool_info

    monkeypatch.delenv("GVBENCH_THREADS", raising=False)
    monkeypatch.setattr(concurrency, "available_cores", lambda: 4)
    before = torch.get_num_threads(), cv2.getNumThreads()
    try:
        assert concurrency.configure_threads(jobs=2) == 2
        assert cv2.getNumThreads() == 2 and torch.get_num_threads() == 1
        assert {pool["num_threads"] for pool in threadpool_info() if pool["user_api"] == "blas"} <= {1}
        assert concurrency.configure_threads(jobs=8) == 1  # never fewer than one a job
        assert concurrency.configure_threads(3, jobs=2) == 3  # asked for
        monkeypatch.setenv("GVBENCH_THREADS", "2")
        assert concurrency.configure_threads(jobs=4) == 2
    finally:
        torch.set_num_threads(before[0])
        cv2.setNumThreads(before[1])


def test_run_jobs_flag_is_exported_for_the_notebook_kernels_and_checked_like_the_variable(monkeypatch, capsys):
    from gvbench_nb import cli

    monkeypatch.delenv("GVBENCH_JOBS", raising=False)
    args = cli.build_parser().parse_args(["run", "p.yaml", "--jobs", "2", "--dask-workers", "3"])
    assert args.jobs == 2 and os.environ["GVBENCH_JOBS"] == "2" and concurrency.job_count() == 2
    assert args.dask_workers == 3  # the Dask cluster's size: another name, another number
    monkeypatch.delenv("GVBENCH_JOBS")
    assert cli.build_parser().parse_args(["run", "p.yaml"]).jobs is None
    monkeypatch.setenv("GVBENCH_JOBS", "0")
    with pytest.raises(SystemExit) as stopped:  # a bad variable is refused at parse time, before any work
        cli.build_parser().parse_args(["run", "p.yaml"])
    assert stopped.value.code == 2
    assert "argument --jobs: must be a whole number of at least 1 (--jobs or $GVBENCH_JOBS), got '0'" in (
        capsys.readouterr().err
    )
    monkeypatch.delenv("GVBENCH_JOBS")
    with pytest.raises(SystemExit):  # the old spelling is gone, not an alias
        cli.build_parser().parse_args(["run", "p.yaml", "--workers", "2"])
    assert "unrecognized arguments: --workers 2" in capsys.readouterr().err


# ---------------------------------------------------- past one machine: real processes --
CLI_METHODS, CLI_LIMIT = ("orb-nn", "sift-nn"), "32"
DASK = Path(sys.executable).parent / "dask"  # Dask's own command line, of the environment under test
TABLE_HEADER = ["method", "profile", "n_pairs", "n_positives", "ap", "max_recall", "seconds_per_pair", "timers"]


def run_argv(params: Path, output: Path, *more: str) -> list[str]:
    methods_option = ["--methods", ",".join(CLI_METHODS), "--limit", CLI_LIMIT]
    return [sys.executable, "-m", "gvbench_nb", "run", str(params), *methods_option, "--output-dir", str(output), *more]


def package_environment(cache: Path | None = None, **more: str) -> dict[str, str]:
    """This environment importing the package under test, one thread a job (the machine's cores are
    shared), with a feature cache of the run's own (``cache``) so its timers are its own work."""
    own = {"GVBENCH_CACHE": str(cache)} if cache else {}
    return {**os.environ, "PYTHONPATH": str(config.PROJECT_ROOT), "GVBENCH_THREADS": "1", **own, **more}


def run_to_the_end(argv: list[str], timeout: float = 600, **options) -> subprocess.CompletedProcess:
    """``subprocess.run``, whose whole process group is killed should it outlive ``timeout``."""
    with subprocess.Popen(
        argv, start_new_session=True, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, **options
    ) as process:
        try:
            out, err = process.communicate(timeout=timeout)
        finally:
            if process.poll() is None:
                os.killpg(process.pid, signal.SIGKILL)
                process.wait(timeout=30)
    return subprocess.CompletedProcess(argv, process.returncode, out, err)


def printed_table(stdout: str) -> dict[str, dict[str, str]]:
    """The table ``run`` printed, by method, without its seconds."""
    lines = stdout.splitlines()
    start = next(i for i, line in enumerate(lines) if line.split()[:2] == TABLE_HEADER[:2])
    assert lines[start].split() == TABLE_HEADER
    rows = [line.split() for line in lines[start + 1 : start + 1 + len(CLI_METHODS)]]
    return {cells[0]: {**dict(zip(TABLE_HEADER[1:6], cells[1:6])), "timers": " ".join(cells[7:])} for cells in rows}


def assert_same_results(output: Path, plain: Path) -> None:
    """Both folders' pair tables and results tables are equal, seconds (and when) aside."""
    for method in CLI_METHODS:
        pd.testing.assert_frame_equal(
            without_timings(scoring.load_pairs_table(output, method)),
            without_timings(scoring.load_pairs_table(plain, method)),
        )

    def kept(table: pd.DataFrame) -> pd.DataFrame:
        dropped = [c for c in table.columns if "seconds" in c or c in ("jobs", "finished_at")]
        return table.drop(columns=dropped).sort_values("method").reset_index(drop=True)

    pd.testing.assert_frame_equal(kept(pd.read_csv(output / "results.csv")), kept(pd.read_csv(plain / "results.csv")))


@pytest.fixture(scope="module")
def plain_run(tmp_path_factory) -> tuple[Path, Path, dict[str, dict[str, str]]]:
    """The embedded sample sequence's params (images rendered into a folder of its own), the output
    folder of a plain ``run`` of the first pairs, and the table it printed."""
    folder = tmp_path_factory.mktemp("sample")
    params = folder / "params.yaml"
    sample = {"sequence": "sample", "pairs_builder": "sample", "builder_options": {}, "image_root": "data"}
    sample |= {"pairs": "data/pairs.txt", "methods": list(CLI_METHODS), "profile": PROFILE, "seed": 0}
    params.write_text(yaml.safe_dump(sample | {"output_dir": "plain/out"}))
    done = run_to_the_end(
        run_argv(params, folder / "plain" / "out"), cwd=folder, env=package_environment(folder / "plain" / "cache")
    )
    assert done.returncode == 0, done.stderr[-3000:]
    return params, folder / "plain" / "out", printed_table(done.stdout)


def stop(process: subprocess.Popen) -> None:
    """End ``process`` and its process group: SIGTERM, then SIGKILL, each wait bounded."""
    for stopping in (signal.SIGTERM, signal.SIGKILL):
        if process.poll() is not None:
            return
        with contextlib.suppress(ProcessLookupError):
            os.killpg(process.pid, stopping)
        with contextlib.suppress(subprocess.TimeoutExpired):
            process.wait(timeout=20)


@contextlib.contextmanager
def dask_cluster(folder: Path, worker_paths: list[Path]) -> Iterator[tuple[str, list[tuple[str, subprocess.Popen]]]]:
    """``dask scheduler`` and one ``dask worker`` a PYTHONPATH of ``worker_paths``, started with Dask's
    own command line in ``folder``, on 127.0.0.1 ports the system chose; yields the scheduler's
    address and each worker's (address, process), in the order of ``worker_paths``. Every process
    is stopped after, whatever happened."""
    from distributed import Client

    folder.mkdir()
    local = ["--host", "127.0.0.1", "--no-dashboard"]
    started: list[subprocess.Popen] = []
    with contextlib.ExitStack() as logs:

        def start(name: str, argv: list[str], env: dict[str, str]) -> subprocess.Popen:
            log = logs.enter_context(open(folder / f"{name}.log", "w"))
            started.append(
                subprocess.Popen(
                    [str(DASK), *argv],
                    cwd=folder,
                    env=env,
                    stdout=log,
                    stderr=subprocess.STDOUT,
                    start_new_session=True,
                )
            )
            return started[-1]

        try:
            scheduler_file = folder / "scheduler.json"
            scheduler = start(
                "scheduler",
                ["scheduler", "--port", "0", "--scheduler-file", str(scheduler_file), *local],
                package_environment(),
            )
            address = wait_for_address(scheduler_file, scheduler)
            for i, path in enumerate(worker_paths):
                start(
                    f"worker-{i}",
                    ["worker", address, "--nthreads", "1", "--no-nanny", "--local-directory", f"space-{i}", *local],
                    package_environment(PYTHONPATH=str(path)),
                )
            with Client(address, timeout=60) as client:
                client.wait_for_workers(len(worker_paths), timeout=120)
                pids = client.run(os.getpid)
            workers = sorted(
                ((w, p) for w, pid in pids.items() for p in started if p.pid == pid),
                key=lambda worker: started.index(worker[1]),
            )
            yield address, workers
        finally:
            for process in reversed(started):
                stop(process)


def wait_for_address(scheduler_file: Path, scheduler: subprocess.Popen, timeout: float = 120) -> str:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        assert scheduler.poll() is None, (
            "dask scheduler ended: " + (scheduler_file.parent / "scheduler.log").read_text()
        )
        with contextlib.suppress(OSError, ValueError, KeyError):
            return json.loads(scheduler_file.read_text())["address"]
        time.sleep(0.2)
    pytest.fail(f"dask scheduler wrote no {scheduler_file} in {timeout} s")


@pytest.mark.slow
@pytest.mark.reliability
def test_a_run_on_a_dask_cluster_started_from_its_command_line_equals_the_plain_run(plain_run, tmp_path):
    params, plain, plain_table = plain_run
    output = tmp_path / "dask" / "out"
    with dask_cluster(tmp_path / "cluster", [config.PROJECT_ROOT] * 2) as (address, _):
        argv = run_argv(params, output, "--dask", "--scheduler", address, "--shards", "4")
        done = run_to_the_end(argv, cwd=params.parent, env=package_environment(output.parent / "cache"))
    assert done.returncode == 0, done.stderr[-3000:]
    assert printed_table(done.stdout) == plain_table  # timers included: "this run" on both sides
    assert {row["timers"] for row in plain_table.values()} == {"this run"}
    assert_same_results(output, plain)


@pytest.mark.slow
@pytest.mark.reliability
def test_a_dask_worker_killed_mid_run_leaves_the_table_identical(plain_run, tmp_path):
    from distributed import Client

    params, plain, plain_table = plain_run
    output = tmp_path / "dask" / "out"
    argv = run_argv(params, output, "--dask", "--scheduler", "ADDRESS", "--shards", "4")
    with (
        dask_cluster(tmp_path / "cluster", [config.PROJECT_ROOT] * 2) as (address, workers),
        open(tmp_path / "run.out", "w+") as out,
        open(tmp_path / "run.err", "w+") as err,
    ):
        argv[argv.index("ADDRESS")] = address
        run = subprocess.Popen(
            argv, cwd=params.parent, env=package_environment(output.parent / "cache"), stdout=out, stderr=err
        )
        try:
            with Client(address, timeout=60) as client:
                busy = busy_worker(client, run)
            killed = dict(workers)[busy]
            os.kill(killed.pid, signal.SIGKILL)  # while it runs a task of the run
            assert killed.wait(timeout=30) == -signal.SIGKILL and run.poll() is None
            code = run.wait(timeout=600)
        finally:
            stop(run)
        out.seek(0), err.seek(0)
        stdout, stderr = out.read(), err.read()
    assert code == 0, stderr[-3000:]
    assert printed_table(stdout) == plain_table
    assert_same_results(output, plain)


def busy_worker(client, run: subprocess.Popen, timeout: float = 300) -> str:
    """The address of the first worker seen running a task while ``run`` goes on."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        assert run.poll() is None, "the run ended before a worker was seen running one of its tasks"
        busy = [worker for worker, keys in client.processing().items() if keys]
        if busy:
            return busy[0]
        time.sleep(0.05)
    pytest.fail(f"no worker ran a task within {timeout} s")


@pytest.mark.slow
@pytest.mark.reliability
def test_a_dask_worker_of_another_version_is_refused_in_one_sentence_before_any_folder(plain_run, tmp_path):
    params = plain_run[0]
    other = tmp_path / "other"  # the package under test with another version: what another release runs
    shutil.copytree(
        config.PROJECT_ROOT / "gvbench_nb", other / "gvbench_nb", ignore=shutil.ignore_patterns("__pycache__")
    )
    init = other / "gvbench_nb" / "__init__.py"
    init.write_text(re.sub(r'__version__ = "[^"]*"', '__version__ = "0.0.0+other"', init.read_text()))
    output = tmp_path / "dask" / "out"
    with dask_cluster(tmp_path / "cluster", [config.PROJECT_ROOT, other]) as (address, workers):
        other_worker = workers[1][0]
        argv = run_argv(params, output, "--dask", "--scheduler", address)
        done = run_to_the_end(argv, cwd=params.parent, env=package_environment(output.parent / "cache"))
    assert done.returncode == 2
    assert re.fullmatch(
        rf"error: Dask worker {re.escape(other_worker)} runs gvbench_nb 0\.0\.0\+other \(code [0-9a-f]{{12}}\) where "
        rf"this process runs {re.escape(__version__)} \(code [0-9a-f]{{12}}\): every worker needs this package at the "
        r"same version and code, and the image root, cache folder and output folder at the same paths on a shared "
        r"filesystem \(docs/speed\.md\)\n",
        done.stderr,
    ), done.stderr
    assert not output.parent.exists()  # no output or cache folder: nothing was done


@pytest.mark.slow
@pytest.mark.reliability
def test_the_slurm_job_array_of_the_docs_gives_the_unsharded_table(plain_run, tmp_path):
    """The docs' sbatch script and submission, run as written by a stand-in sbatch: each shard a
    process of its own, then the merge."""
    params, plain, plain_table = plain_run
    blocks = re.findall(r"```bash\n(.*?)```", (config.PROJECT_ROOT / "docs" / "speed.md").read_text(), re.DOTALL)
    script = next(block for block in blocks if block.startswith("#!/bin/bash\n#SBATCH"))
    submission = next(block for block in blocks if block.startswith("job=$(sbatch"))
    (tmp_path / "shards.sbatch").write_text(script)
    sbatch = tmp_path / "bin" / "sbatch"
    sbatch.parent.mkdir()
    sbatch.write_text(f'#!/bin/sh\nexec "{sys.executable}" "{Path(__file__).parent / "sbatch_here.py"}" "$@"\n')
    sbatch.chmod(0o755)
    output = tmp_path / "slurm" / "out"
    run = " ".join(run_argv(params, output)[4:])  # what follows `python -m gvbench_nb run`
    path = os.pathsep.join([str(sbatch.parent), str(Path(sys.executable).parent), os.environ["PATH"]])
    environment = package_environment(
        output.parent / "cache", PATH=path, RUN=run, SBATCH_HERE_JOBS=str(tmp_path / "jobs")
    )
    done = run_to_the_end(["bash", "-e", "-c", submission], cwd=tmp_path, env=environment)
    assert done.returncode == 0, done.stderr[-3000:]
    shards = sorted(tmp_path.glob("slurm-1_*.out"))
    assert [path.name for path in shards] == [f"slurm-1_{i}.out" for i in range(4)]
    for i, log in enumerate(shards):
        assert f"shard {i}/4 finished" in log.read_text(), log.read_text()[-3000:]
    assert [(tmp_path / "jobs" / f"{job}.status").read_text() for job in (1, 2)] == ["0", "0"]
    assert printed_table((tmp_path / "slurm-2.out").read_text()) == plain_table
    assert_same_results(output, plain)
