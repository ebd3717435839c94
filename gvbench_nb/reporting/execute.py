"""Executing a notebook with papermill: how `run` and `report` keep each notebook as the record of its step."""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Any

NOTEBOOKS_DIR = Path(__file__).resolve().parents[2] / "notebooks"


def execute_notebook(name: str, output_path: Path, parameters: dict[str, Any]) -> None:
    # jsonschema (under papermill's nbformat) compiles an IRI grammar at import when
    # rfc3987-syntax is installed: more CPU than the rest of papermill's import, for a
    # format no notebook schema uses. Without it jsonschema simply lacks that checker.
    sys.modules.setdefault("rfc3987_syntax", None)  # type: ignore[arg-type]
    import papermill

    output_path.parent.mkdir(parents=True, exist_ok=True)
    # Kernel stderr (the stages' tqdm bars) goes to the terminal, so long runs show progress.
    # The kernel starts in notebooks/ through nbclient's resources rather than papermill's
    # cwd, which changes this whole process's folder and is unsafe for notebooks run in threads.
    papermill.execute_notebook(
        str(NOTEBOOKS_DIR / name),
        str(output_path),
        parameters=parameters,
        resources={"metadata": {"path": str(NOTEBOOKS_DIR)}},
        progress_bar=False,
        stderr_file=sys.stderr,
        kernel_name="python3",
    )
