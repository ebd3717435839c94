"""A command or notebook that runs no model imports no model library.

Each check runs in a fresh interpreter, since this test process has imported torch long before.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path
from typing import Any

import pandas as pd
import pytest

from gvbench_nb.runner import method_outputs

PROJECT = Path(__file__).resolve().parents[2]
HEAVY = ("torch", "kornia", "sklearn", "seaborn", "matplotlib")


def modules_after(code: str, env: dict[str, str] | None = None) -> dict:
    """Run ``code`` in a new interpreter; return which HEAVY modules it imported and what it printed."""
    probe = (
        f"{code}\nimport json, sys\n"
        f"print(json.dumps({{'imported': [m for m in {HEAVY!r} if m in sys.modules], 'out': OUT}}))"
    )
    environment = {**os.environ, "PYTHONPATH": str(PROJECT), **(env or {})}
    done = subprocess.run(
        [sys.executable, "-c", probe], capture_output=True, text=True, cwd=PROJECT, env=environment, timeout=300
    )
    assert done.returncode == 0, done.stderr
    return json.loads(done.stdout.strip().splitlines()[-1])


@pytest.mark.slow
def test_help_imports_no_model_library():
    found = modules_after(
        "import runpy, sys\nsys.argv = ['gvbench_nb', '--help']\nOUT = None\n"
        "try:\n    runpy.run_module('gvbench_nb', run_name='__main__')\nexcept SystemExit as exit:\n    OUT = exit.code"
    )
    assert found["out"] in (0, None)
    assert found["imported"] == []


def stage_notebook_imports() -> str:
    """The import cells of the stage notebooks (the code above each parameters cell)."""
    import jupytext

    cells = []
    for name in ("01_sequence", "02_verify", "03_evaluate"):
        code = [c for c in jupytext.read(PROJECT / "notebooks" / f"{name}.py").cells if c.cell_type == "code"]
        first = next(i for i, c in enumerate(code) if "parameters" in c.metadata.get("tags", []))
        cells += [c.source for c in code[:first]]
    return "\n".join(cells)


@pytest.mark.slow
def test_stage_notebook_setup_imports_no_torch_kornia_sklearn_or_seaborn():
    # What every stage notebook imports before its work; only a 02_verify with work to do then imports the models.
    imports = stage_notebook_imports()
    assert "gvbench_nb" in imports
    found = modules_after(f"{imports}\nOUT = None")
    assert [m for m in found["imported"] if m != "matplotlib"] == []


@pytest.mark.slow
@pytest.mark.parametrize(
    "env",
    [
        {"TORCH_HOME": "/tmp/a torch home"},
        {"XDG_CACHE_HOME": "/tmp/xdg cache"},
        {"TORCH_HOME": "~/th", "XDG_CACHE_HOME": "/tmp/ignored"},
        {},
    ],
)
def test_checkpoint_folder_without_torch_is_torch_hubs(env):
    clean = {k: "" for k in ("TORCH_HOME", "XDG_CACHE_HOME") if k not in env}
    code = (
        "import os\n"
        + "".join(f"os.environ.pop({k!r}, None)\n" for k in clean)
        + "from gvbench_nb.protocol import weights\nbefore = str(weights.checkpoints_dir())\n"
        "assert 'torch' not in __import__('sys').modules\n"
        "import torch\nOUT = [before, os.path.join(torch.hub.get_dir(), 'checkpoints'), "
        "str(weights.checkpoints_dir())]"
    )
    found = modules_after(code, env)
    without_torch, torch_answer, with_torch = found["out"]
    assert without_torch == torch_answer == with_torch


# Put first on PYTHONPATH, this records in $GVBENCH_IMPORT_PROBE each process that starts
# (its command line) and each model library it imports, however deep the import.
IMPORT_PROBE = """\
import json, os, sys
_folder = os.environ.get("GVBENCH_IMPORT_PROBE")
if _folder:
    _seen = set()

    def _mark(name):
        with open(os.path.join(_folder, f"{os.getpid()}.{name}"), "w") as handle:
            json.dump(sys.orig_argv, handle)

    def _hook(event, args):
        if event == "import":
            top = str(args[0]).partition(".")[0]
            if top in ("torch", "kornia") and top not in _seen:
                _seen.add(top)
                _mark(top)

    _mark("started")
    sys.addaudithook(_hook)
"""


def tiny_sample_params(tmp_path: Path, methods: list[str]) -> Path:
    """A params file of the synthetic route, 6 frames of 160x120, first 6 pairs (one false)."""
    path = tmp_path / "tiny.yaml"
    path.write_text(
        "sequence: tiny\npairs_builder: sample\nbuilder_options: {n_frames: 6, image_size: [160, 120]}\n"
        f"image_root: {tmp_path / 'data'}\npairs: {tmp_path / 'data' / 'pairs.txt'}\nmethods: {methods}\n"
        f"profile: repository\noutput_dir: {tmp_path / 'out'}\nlimit: 6\nseed: 0\n"
    )
    return path


@pytest.mark.slow
def test_a_run_imports_torch_once_and_its_notebooks_find_every_result_done(tmp_path):
    """``run`` computes every method in its own process; the notebooks it then executes
    (the record of the run) find each method's result done and import no model library."""
    probe, marks = tmp_path / "probe", tmp_path / "marks"
    probe.mkdir()
    marks.mkdir()
    (probe / "sitecustomize.py").write_text(IMPORT_PROBE)
    methods = ["sift-nn", "orb-nn"]
    environment = {
        **os.environ,
        "PYTHONPATH": f"{probe}{os.pathsep}{PROJECT}",
        "GVBENCH_IMPORT_PROBE": str(marks),
        "GVBENCH_THREADS": "1",
    }
    done = subprocess.run(
        [sys.executable, "-m", "gvbench_nb", "run", str(tiny_sample_params(tmp_path, methods))],
        capture_output=True,
        text=True,
        cwd=tmp_path,
        env=environment,
        timeout=600,
    )
    assert done.returncode == 0, done.stderr[-3000:]
    assert "results table:" in done.stdout

    processes: dict[str, dict[str, Any]] = {}
    for mark in marks.iterdir():
        pid, name = mark.name.split(".", 1)
        processes.setdefault(pid, {"argv": json.loads(mark.read_text()), "imported": set()})
        if name != "started":
            processes[pid]["imported"].add(name)
    kernels = [p for p in processes.values() if "ipykernel_launcher" in " ".join(p["argv"])]
    command = [p for p in processes.values() if "gvbench_nb" in p["argv"] and "run" in p["argv"]]
    assert len(kernels) == 2 + len(methods)  # 01_sequence, 02_verify a method, 03_evaluate
    assert [k["imported"] for k in kernels] == [set()] * len(kernels)
    assert len(command) == 1 and "torch" in command[0]["imported"]

    out = tmp_path / "out"
    for method in methods:
        run = json.loads((method_outputs.method_dir(out, method) / "run.json").read_text())
        # run.json records the work this run did, in the command; the notebook found it done.
        assert run["this_run"]["extraction"] == {"images": 7, "cached": 0, "extracted": 7}
        assert run["this_run"]["matching"] == {"pairs": 6, "cached": 0, "matched": 6}
        assert run["environment"]["torch"]
        assert (method_outputs.method_dir(out, method).parent / f"02_verify_{method}.ipynb").is_file()
    assert list(pd.read_csv(out / "results.csv")["method"]) == methods
