"""A command or notebook that runs no model imports no model library.

Each check runs in a fresh interpreter, since this test process has imported torch long before.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

PROJECT = Path(__file__).resolve().parent.parent
HEAVY = ("torch", "kornia", "sklearn", "seaborn", "matplotlib")


def modules_after(code: str, env: dict[str, str] | None = None) -> dict:
    """Run ``code`` in a new interpreter; return which HEAVY modules it imported and what it printed."""
    probe = (f"{code}\nimport json, sys\n"
             f"print(json.dumps({{'imported': [m for m in {HEAVY!r} if m in sys.modules], 'out': OUT}}))")
    environment = {**os.environ, "PYTHONPATH": str(PROJECT), **(env or {})}
    done = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, cwd=PROJECT, env=environment,
                          timeout=300)
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
    # What every stage notebook imports before its work; only 02_verify's run then imports the models.
    imports = stage_notebook_imports()
    assert "gvbench_nb" in imports
    found = modules_after(f"{imports}\nOUT = None")
    assert [m for m in found["imported"] if m != "matplotlib"] == []


@pytest.mark.slow
@pytest.mark.parametrize("env", [
    {"TORCH_HOME": "/tmp/a torch home"},
    {"XDG_CACHE_HOME": "/tmp/xdg cache"},
    {"TORCH_HOME": "~/th", "XDG_CACHE_HOME": "/tmp/ignored"},
    {},
])
def test_checkpoint_folder_without_torch_is_torch_hubs(env):
    clean = {k: "" for k in ("TORCH_HOME", "XDG_CACHE_HOME") if k not in env}
    code = ("import os\n" + "".join(f"os.environ.pop({k!r}, None)\n" for k in clean) +
            "from gvbench_nb import weights\nbefore = str(weights.checkpoints_dir())\n"
            "assert 'torch' not in __import__('sys').modules\n"
            "import torch\nOUT = [before, os.path.join(torch.hub.get_dir(), 'checkpoints'), "
            "str(weights.checkpoints_dir())]")
    found = modules_after(code, env)
    without_torch, torch_answer, with_torch = found["out"]
    assert without_torch == torch_answer == with_torch
