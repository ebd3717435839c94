"""A `run` computes each method, and each pair, once, in its own process, not again in the kernels:
every process counts its calls into one file through a ``sitecustomize`` import hook."""

from __future__ import annotations

import os
import subprocess
import sys
from collections import Counter

import pandas as pd
import pytest
import yaml

from gvbench_nb.runner import config, runs

METHODS = ("orb-nn", "sift-nn")
LIMIT = 6

# Wraps the functions below as their modules load; each call appends "pid function what" to $GVBENCH_TEST_CALLS.
COUNTING_HOOK = """
import functools, importlib.abc, importlib.machinery, os, sys

WATCHED = {
    "gvbench_nb.runner.pair_matching": ("_verify_pair",),
    "gvbench_nb.runner.method_runs": ("compute_method", "pairs_table"),
}
WHAT = {  # from the positional arguments: the method (and the pair) a call works on
    "_verify_pair": lambda args: f"{args[1]['method']} {args[0].query} {args[0].reference}",
    "compute_method": lambda args: args[1]["method"],
    "pairs_table": lambda args: args[1]["method"],
}


def counted(name, function):
    @functools.wraps(function)
    def wrapper(*args, **kwargs):
        with open(os.environ["GVBENCH_TEST_CALLS"], "a", encoding="utf-8") as stream:
            stream.write(f"{os.getpid()} {name} {WHAT[name](args)}\\n")
        return function(*args, **kwargs)

    return wrapper


class Counting(importlib.abc.MetaPathFinder):
    def find_spec(self, fullname, path, target=None):
        if fullname not in WATCHED:
            return None
        spec = importlib.machinery.PathFinder.find_spec(fullname, path)
        execute = spec.loader.exec_module

        def exec_module(module):
            execute(module)
            for name in WATCHED[fullname]:
                setattr(module, name, counted(name, getattr(module, name)))

        spec.loader.exec_module = exec_module
        return spec


sys.meta_path.insert(0, Counting())
"""


@pytest.mark.slow
def test_a_run_of_two_methods_computes_each_method_and_pair_once_in_one_process(tmp_path):
    raw = yaml.safe_load((config.PROJECT_ROOT / "params" / "sample.yaml").read_text())
    raw.update(image_root="data", pairs="data/pairs.txt", output_dir="out", methods=list(METHODS), limit=LIMIT)
    params = tmp_path / "sample.yaml"
    params.write_text(yaml.safe_dump(raw))
    hook, calls = tmp_path / "hook", tmp_path / "calls.txt"
    hook.mkdir()
    (hook / "sitecustomize.py").write_text(COUNTING_HOOK)
    done = subprocess.run(
        [sys.executable, "-m", "gvbench_nb", "run", str(params), "--jobs", "1"],
        capture_output=True,
        text=True,
        timeout=900,
        cwd=tmp_path,
        env={
            **os.environ,
            "PYTHONPATH": os.pathsep.join([str(hook), str(config.PROJECT_ROOT)]),
            "GVBENCH_TEST_CALLS": str(calls),
            "GVBENCH_THREADS": "1",
        },
    )
    assert done.returncode == 0, done.stderr[-3000:]
    lines = [line.split(" ", 2) for line in calls.read_text().splitlines()]
    assert len({pid for pid, _, _ in lines}) == 1  # the command's process; no notebook kernel computed
    counts = Counter((name, what) for _, name, what in lines)
    for method in METHODS:
        assert counts[("compute_method", method)] == 1 and counts[("pairs_table", method)] == 1
        verified = {what: n for (name, what), n in counts.items() if name == "_verify_pair" and what.startswith(method)}
        assert len(verified) == LIMIT and set(verified.values()) == {1}, verified
    # The notebooks ran in the run, reading what it computed.
    ((run, _),) = runs.finished_runs(tmp_path / "out")
    assert all((run / f"02_verify_{m}.ipynb").is_file() for m in METHODS)
    assert sorted(pd.read_csv(tmp_path / "out" / "results.csv")["method"]) == sorted(METHODS)
