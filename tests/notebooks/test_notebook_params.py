"""A stage notebook's parameters are enough: ``papermill notebooks/02_verify.ipynb OUT.ipynb -f P.yaml``
with P.yaml a complete params file kept anywhere (not in params/) runs on its keys, from the repository
root or any other folder; its relative paths are read from the working folder, which the notebook prints."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
import yaml
from helpers import PAIRS, papermill_from, write_root

from gvbench_nb.data.sequences import write_pairs
from gvbench_nb.runner import config


def complete_params(folder: Path, relative_to: Path | None = None) -> Path:
    """``folder/p.yaml``: every params key, orb-nn on the four photographs (sequence 'pmf', no params file
    of it in params/); its paths absolute, or relative to ``relative_to``."""
    write_root(folder / "images")
    write_pairs(folder / "pairs.txt", PAIRS)
    paths = {"pairs": folder / "pairs.txt", "image_root": folder / "images"}
    paths |= {"output_dir": folder / "out", "cache_dir": folder / "cache"}
    given = {k: str(p if relative_to is None else os.path.relpath(p, relative_to)) for k, p in paths.items()}
    keys = {**config.OPTIONAL_KEYS, "sequence": "pmf", "methods": ["orb-nn"], "profile": "paper", "limit": 4, **given}
    assert set(keys) == set(config.ParamsModel.model_fields)  # every key
    path = folder / "p.yaml"
    path.write_text(yaml.safe_dump(keys, sort_keys=False))
    return path


def results_row(output_dir: Path, method: str) -> dict[str, str]:
    """``python -m gvbench_nb results OUTPUT_DIR --markdown`` (expected to exit 0): ``method``'s row."""
    done = subprocess.run(
        [sys.executable, "-m", "gvbench_nb", "results", str(output_dir), "--markdown"],
        capture_output=True,
        text=True,
        timeout=300,
        env={**os.environ, "PYTHONPATH": str(config.PROJECT_ROOT)},
    )
    assert done.returncode == 0, done.stderr[-3000:]
    rows = [
        [cell.strip() for cell in line.strip("|").split("|")] for line in done.stdout.splitlines() if line[:1] == "|"
    ]
    header = rows[0]
    return next(dict(zip(header, row)) for row in rows[2:] if row[0] == method)


@pytest.mark.reliability
def test_a_complete_params_file_kept_elsewhere_runs_02_verify_from_the_repository_root(tmp_path):
    study = tmp_path / "my" / "study"
    said = papermill_from(
        config.PROJECT_ROOT,
        "02_verify",
        tmp_path / "02_verify.ipynb",
        "-f",
        complete_params(study),
        "-p",
        "method",
        "orb-nn",
    )
    assert f"the notebook's parameters (no params_file); relative paths are read from {config.PROJECT_ROOT}" in said
    row = results_row(study / "out", "orb-nn")
    assert row["n_pairs"] == "4" and row["profile"] == "paper"


@pytest.mark.reliability
def test_a_complete_params_file_with_relative_paths_runs_02_verify_from_another_folder(tmp_path):
    elsewhere = tmp_path / "work"
    elsewhere.mkdir()
    params = complete_params(tmp_path / "my" / "study", relative_to=elsewhere)
    assert yaml.safe_load(params.read_text())["output_dir"] == "../my/study/out"
    said = papermill_from(elsewhere, "02_verify", tmp_path / "02_verify.ipynb", "-f", params, "-p", "method", "orb-nn")
    assert f"the notebook's parameters (no params_file); relative paths are read from {elsewhere}" in said
    row = results_row(tmp_path / "my" / "study" / "out", "orb-nn")
    assert row["n_pairs"] == "4" and row["profile"] == "paper"
