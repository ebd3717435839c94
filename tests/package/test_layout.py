"""The package's layout holds: pyproject.toml's import contracts (imports inside functions count too),
a small protocol, and every folder the docs name."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
PACKAGE = REPO / "gvbench_nb"
STAGES = ("protocol", "protocol/features", "protocol/matching", "protocol/recipes", "data", "runner")
STAGES += ("evaluation", "verification", "studies", "reporting")
PROTOCOL_LINES = 3200  # about 3,000 (with the recipes' references): a reviewer reads it against hloc in one sitting
LINT_IMPORTS = str(Path(sys.executable).with_name("lint-imports"))


def lint_imports(folder: Path) -> subprocess.CompletedProcess[str]:
    """lint-imports on the package and pyproject.toml found in ``folder``."""
    env = {**os.environ, "PYTHONPATH": str(folder)}
    return subprocess.run([LINT_IMPORTS, "--no-cache"], cwd=folder, env=env, capture_output=True, text=True)


def test_the_import_contracts_hold() -> None:
    result = lint_imports(REPO)
    assert result.returncode == 0, result.stdout + result.stderr
    assert "4 kept, 0 broken" in result.stdout


def empty_package(folder: Path) -> Path:
    """A package with this project's rooms and the modules its contracts name, empty, under its own contracts."""
    config = (REPO / "pyproject.toml").read_text().split("[tool.importlinter]", 1)[1]
    (folder / "pyproject.toml").write_text("[tool.importlinter]" + config)
    package = folder / "gvbench_nb"
    rooms = {path.stem for path in PACKAGE.iterdir() if path.suffix == ".py" or path.is_dir()}
    for room in rooms - {"__pycache__", "__init__"}:
        (package / room).mkdir(parents=True)
        (package / room / "__init__.py").write_text("")
    (package / "__init__.py").write_text("")
    for module in re.findall(r'"gvbench_nb\.runner\.(\w+)"', config):
        (package / "runner" / f"{module}.py").write_text("")
    return package


def test_the_layer_contract_finds_an_import_back_up(tmp_path: Path) -> None:
    package = empty_package(tmp_path)
    (package / "protocol" / "images.py").write_text("def load():\n    from gvbench_nb.runner import store\n")
    (package / "runner" / "store.py").write_text("")
    result = lint_imports(tmp_path)
    assert result.returncode != 0
    assert "gvbench_nb.protocol.images -> gvbench_nb.runner.store" in result.stdout


def test_the_stage_contract_finds_a_stage_that_knows_an_output_folder(tmp_path: Path) -> None:
    package = empty_package(tmp_path)
    (package / "runner" / "pair_matching.py").write_text("def store():\n    from gvbench_nb.runner import runs\n")
    result = lint_imports(tmp_path)
    assert result.returncode != 0
    assert "the stages know no output folder BROKEN" in result.stdout
    assert "gvbench_nb.runner.pair_matching -> gvbench_nb.runner.runs" in result.stdout


def test_each_stage_is_a_folder_of_the_package() -> None:
    for stage in STAGES:
        assert (PACKAGE / stage / "__init__.py").is_file(), stage


def test_the_protocol_stays_small() -> None:
    files = [*(PACKAGE / "protocol").rglob("*.py"), *(PACKAGE / "protocol").rglob("*.yaml")]
    lines = sum(len(path.read_text().splitlines()) for path in files)
    assert lines <= PROTOCOL_LINES, f"protocol/ holds {lines} lines"
