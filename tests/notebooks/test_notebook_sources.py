"""Each notebook and its jupytext percent-format twin agree, carry no outputs, and have one
``parameters`` cell with only imports above it."""

from __future__ import annotations

import ast
import json
from pathlib import Path

import jupytext
import pytest

NOTEBOOKS = Path(__file__).resolve().parents[2] / "notebooks"
IPYNB = sorted(NOTEBOOKS.glob("*.ipynb"))
SYNC = "run `jupytext --sync notebooks/{name}` (the newer file of the two wins)"


def cells(path: Path) -> list[tuple[str, str, list[str]]]:
    """(type, source, tags) of every cell, as jupytext reads the file."""
    notebook = jupytext.read(path)
    return [(c.cell_type, c.source.strip("\n"), list(c.metadata.get("tags", []))) for c in notebook.cells]


def test_every_notebook_has_its_twin_and_every_twin_its_notebook():
    assert IPYNB, f"no notebooks in {NOTEBOOKS}"
    scripts = {p.stem for p in NOTEBOOKS.glob("*.py")}
    notebooks = {p.stem for p in IPYNB}
    assert not notebooks - scripts, (
        f"notebooks without a .py twin: {sorted(notebooks - scripts)}; pair each with "
        "`jupytext --set-formats ipynb,py:percent notebooks/NAME.ipynb`"
    )
    assert not scripts - notebooks, (
        f"scripts in notebooks/ without a notebook: {sorted(scripts - notebooks)}; "
        "make one with `jupytext --sync notebooks/NAME.py` or move the script"
    )


@pytest.mark.parametrize("path", IPYNB, ids=lambda p: p.name)
def test_notebook_and_script_agree(path):
    script = path.with_suffix(".py")
    if not script.is_file():
        pytest.skip(f"{script.name} is missing (reported by the pairing test)")
    formats = jupytext.read(path).metadata.get("jupytext", {}).get("formats")
    assert formats == "ipynb,py:percent", (
        f"{path.name}: jupytext formats {formats!r}, not 'ipynb,py:percent'; "
        f"run `jupytext --set-formats ipynb,py:percent notebooks/{path.name}`"
    )
    ours, theirs = cells(path), cells(script)
    for index, (a, b) in enumerate(zip(ours, theirs)):
        assert a == b, f"{path.name} and {script.name} differ at cell {index}: {SYNC.format(name=path.name)}"
    assert len(ours) == len(theirs), (
        f"{path.name} has {len(ours)} cells, {script.name} {len(theirs)}: {SYNC.format(name=path.name)}"
    )


@pytest.mark.parametrize("path", IPYNB, ids=lambda p: p.name)
def test_notebook_is_committed_without_outputs(path):
    raw = json.loads(path.read_text())
    dirty = [
        i
        for i, c in enumerate(raw["cells"])
        if c["cell_type"] == "code" and (c.get("outputs") or c.get("execution_count") is not None)
    ]
    assert not dirty, (
        f"{path.name}: cells {dirty} hold outputs; clear them with "
        f"`jupyter nbconvert --clear-output --inplace notebooks/{path.name}`"
    )


@pytest.mark.parametrize("path", IPYNB, ids=lambda p: p.name)
def test_notebook_has_one_parameters_cell_and_only_imports_above_it(path):
    code = [c for c in jupytext.read(path).cells if c.cell_type == "code"]
    tagged = [i for i, c in enumerate(code) if "parameters" in c.metadata.get("tags", [])]
    assert len(tagged) == 1, (
        f"{path.name}: {len(tagged)} parameters-tagged code cells, want one "
        '(`# %% tags=["parameters"]` in the .py): papermill injects its values after it'
    )
    # Code above the parameters cell runs before papermill's values arrive: imports only.
    for index, cell in enumerate(code[: tagged[0]]):
        statements = ast.parse(cell.source).body
        assert all(isinstance(s, (ast.Import, ast.ImportFrom)) for s in statements), (
            f"{path.name}: code cell {index}, above the parameters cell, does more than import; "
            "move that code below the parameters cell"
        )
