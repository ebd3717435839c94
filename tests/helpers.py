"""Helpers the tests share (fixtures stay in conftest.py)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pandas as pd
import pytest
import yaml

from gvbench_nb import cli, notebook
from gvbench_nb.data.sequences import Pair, write_pairs
from gvbench_nb.protocol import metrics
from gvbench_nb.runner import config, method_outputs, method_runs, scoring, sequence_build

# Two queries, each with its own view (true) and the other one (false).
PAIRS = [
    Pair("query/a.png", "reference/a.png", 1),
    Pair("query/a.png", "reference/b.png", 0),
    Pair("query/b.png", "reference/b.png", 1),
    Pair("query/b.png", "reference/a.png", 0),
]
FLIPPED = [Pair(p.query, p.reference, 1 - p.label) for p in PAIRS]
# Eight pairs of four photographs (``write_root`` of four): each query with its own view and the next one's.
PAIRS8 = [
    pair
    for this, other in zip("abcd", "bcda")
    for pair in (
        Pair(f"query/{this}.png", f"reference/{this}.png", 1),
        Pair(f"query/{this}.png", f"reference/{other}.png", 0),
    )
]


def photo(name: str, warped: bool, size: tuple[int, int] = (320, 240)) -> np.ndarray:
    """One of scikit-image's photographs, BGR at ``size``; warped (a small rotation and zoom) for a query view."""
    import skimage.data

    image = getattr(skimage.data, name)()
    image = cv2.cvtColor(image, cv2.COLOR_GRAY2RGB) if image.ndim == 2 else image
    image = cv2.resize(image, size, interpolation=cv2.INTER_AREA)
    if warped:
        matrix = cv2.getRotationMatrix2D((size[0] / 2, size[1] / 2), 4.0, 1.05)
        image = cv2.warpAffine(image, matrix, size, borderMode=cv2.BORDER_REFLECT)
    return cv2.cvtColor(image, cv2.COLOR_RGB2BGR)


def write_root(root: Path, photos: tuple[str, ...] = ("astronaut", "coffee"), size=(320, 240)) -> Path:
    """``query/a.png``, ``query/b.png`` (warped) and ``reference/a.png``, ``reference/b.png`` (one letter a photo)."""
    for folder, warped in (("query", True), ("reference", False)):
        (root / folder).mkdir(parents=True, exist_ok=True)
        for letter, name in zip("abcdefgh", photos):
            cv2.imwrite(str(root / folder / f"{letter}.png"), photo(name, warped, size))
    return root


def in_process_notebooks(name: str, output_path: Path, parameters: dict) -> None:
    """What the stage notebooks of a ``run`` compute, here, in place of papermill's
    ``execute_notebook``: 02_verify runs its method, 03_evaluate evaluates."""
    params = notebook.load_params(parameters["params_file"])
    if name == "02_verify.ipynb":
        sequence = sequence_build.prepare_sequence(params)
        method_runs.run_method_of_params(params, sequence, parameters["method"], progress=False)
    elif name == "03_evaluate.ipynb":
        scoring.evaluate(Path(params["output_dir"]), parameters.get("methods"))
    output_path.write_text(json.dumps({"executed": name}))


def params_file(tmp_path: Path, name: str = "params.yaml", pairs: list[Pair] = PAIRS, **changes) -> Path:
    """``tmp_path/name``: orb-nn (repository) on ``tmp_path/images`` and ``pairs``, into ``tmp_path/out``."""
    pairs_path = tmp_path / f"{Path(name).stem}-pairs.txt"
    write_pairs(pairs_path, pairs)
    params = {"sequence": "photos", "image_root": str(tmp_path / "images"), "pairs": str(pairs_path)}
    params |= {"methods": ["orb-nn"], "profile": "repository", "device": "cpu"}
    params |= {"output_dir": str(tmp_path / "out"), "cache_dir": str(tmp_path / "cache"), **changes}
    path = tmp_path / name
    path.write_text(yaml.safe_dump(params))
    return path


def run_cli(capsys, *argv: str) -> tuple[int, str, str]:
    """``cli.main(argv)``: its exit code and what it printed (stdout, stderr)."""
    capsys.readouterr()
    code = cli.main(list(argv))
    said = capsys.readouterr()
    return code, said.out, said.err


def one_sentence(err: str) -> str:
    """``err``, checked to be one line and no traceback."""
    assert "Traceback" not in err and len(err.strip().splitlines()) == 1, err
    return err


def snapshot(folder: Path) -> dict[str, bytes]:
    """Every file under ``folder``: relative path -> bytes."""
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def runs_files(output_dir: Path) -> dict[str, str]:
    """The SHA-256 of every file of the folder's finished runs (``runs/<id>/...``; runs being built left out)."""
    import hashlib

    root = output_dir / "runs"
    return {
        path.relative_to(root).as_posix(): hashlib.sha256(path.read_bytes()).hexdigest()
        for path in sorted(root.rglob("*") if root.is_dir() else [])
        if path.is_file() and not path.relative_to(root).parts[0].startswith(".")
    }


def run_ids(output_dir: Path) -> list[str]:
    """The folder's finished runs' ids, oldest first (read from the files, not through the package)."""
    manifests = [json.loads(path.read_text()) for path in (output_dir / "runs").glob("[!.]*/manifest.json")]
    return [m["run_id"] for m in sorted(manifests, key=lambda m: (m["finished_ns"], m["run_id"]))]


def check_runs_whole(output_dir: Path) -> list[str]:
    """Every finished run under ``runs/`` is whole: its manifest, and each method's ``pairs.csv`` (one row a
    pair of its ``run.json``) and ``run.json`` readable; returns the runs' ids, oldest first."""
    ids = run_ids(output_dir)
    for run_id in ids:
        run = output_dir / "runs" / run_id
        manifest = json.loads((run / "manifest.json").read_text())
        assert manifest["run_id"] == run_id and manifest["door"] in run_id
        for method in manifest["methods"]:
            record = json.loads((run / method / "run.json").read_text())
            assert len(pd.read_csv(run / method / "pairs.csv")) == record["n_pairs"], (run_id, method)
    return ids


def added_one_run(out: Path, before: dict[str, str], door: str) -> str:
    """The one run a door added since ``before`` (``runs_files``), every earlier file unchanged."""
    after = runs_files(out)
    assert {name: after.get(name) for name in before} == before, "an earlier run changed"
    new = sorted({name.split("/")[0] for name in after} - {name.split("/")[0] for name in before})
    assert len(new) == 1 and f"-{door}-" in new[0], new
    return new[0]


def shown(out: Path) -> dict[str, tuple[str, int]]:
    """method -> (profile, n_pairs) of the folder's ``results.csv``."""
    table = pd.read_csv(out / "results.csv")
    return {m: (p, n) for m, p, n in zip(table["method"], table["profile"], table["n_pairs"])}


def not_in_table(err: str) -> list[str]:
    return [line for line in err.splitlines() if line.startswith("not in this table: ")]


def verify_on_its_own(path: Path, method: str = "orb-nn", **overrides) -> None:
    """What ``02_verify`` does when papermill, JupyterLab or nbmake runs it on its own."""
    params = config.load_params(path, **overrides)
    run = notebook.start_run(params, "02_verify")
    sequence = sequence_build.prepare_sequence(params)
    method_runs.run_method_of_params({**params, "output_dir": str(run)}, sequence, method, progress=False)
    notebook.finish_run(params, run)


def write_params(tmp_path: Path, **changes: object) -> Path:
    """``tmp_path/params.yaml``: sift-nn (paper) on ``tmp_path``'s images and pairs.txt, ``changes`` applied."""
    params = {
        "sequence": "s",
        "image_root": str(tmp_path / "images"),
        "pairs": str(tmp_path / "pairs.txt"),
        "methods": ["sift-nn"],
        "profile": "paper",
        "output_dir": str(tmp_path / "out"),
        "cache_dir": str(tmp_path / "cache"),
        "seed": 0,
    }
    params.update(changes)
    path = tmp_path / "params.yaml"
    path.write_text(yaml.safe_dump(params, sort_keys=False))
    return path


def cli_error(capsys, *argv: str) -> str:
    """Run the CLI expecting a user error: exit 2 and one line on stderr, no traceback."""
    capsys.readouterr()
    assert cli.main(list(argv)) == 2
    message = capsys.readouterr().err
    assert "Traceback" not in message and len(message.strip().splitlines()) == 1, message
    return message


def assert_nothing_written(tmp_path: Path) -> None:
    """A refused run made neither ``tmp_path/out`` nor ``tmp_path/cache``."""
    assert not (tmp_path / "out").exists() and not (tmp_path / "cache").exists()


def truncated(source: Path, target: Path) -> Path:
    """``target``: the first half of ``source``'s bytes."""
    data = source.read_bytes()
    target.write_bytes(data[: len(data) // 2])
    return target


def read_layout(reference_dir: Path, name: str) -> dict[str, list[int]]:
    """An official checkpoint's layout: tensor name -> shape ([] for scalars)."""
    path = reference_dir / "layouts" / f"{name}.layout.json"
    if not path.is_file():
        pytest.skip(f"missing {path}")
    return json.loads(path.read_text())


def random_state_dict(layout: dict[str, list[int]]) -> dict:
    """Random tensors in a layout, BatchNorm buffers valid (so a strict load can run)."""
    import torch

    generator = torch.Generator().manual_seed(0)
    state = {}
    for name, shape in layout.items():
        if name.endswith("num_batches_tracked"):
            state[name] = torch.tensor(7, dtype=torch.long)
        elif name.endswith("running_var"):
            state[name] = torch.rand(shape, generator=generator) + 0.5
        else:
            state[name] = torch.randn(shape, generator=generator)
    return state


def with_outlier_matches(rng, p0, p1, n_outliers: int):
    """Planted inlier matches (p0, p1) mixed with uniform random outlier matches in a
    640x480 image, shuffled. Returns points0, points1 and the true inlier mask."""

    o0 = rng.uniform([0, 0], [640, 480], (n_outliers, 2))
    o1 = rng.uniform([0, 0], [640, 480], (n_outliers, 2))
    order = rng.permutation(len(p0) + n_outliers)
    truth = np.r_[np.ones(len(p0), bool), np.zeros(n_outliers, bool)][order]
    return np.r_[p0, o0][order], np.r_[p1, o1][order], truth


def check_stage_outputs(output_dir: Path, method: str, sequence_pairs: list) -> pd.DataFrame:
    """What 02_verify and 03_evaluate wrote for ``method``, against the sequence's pairs
    (``sequences.Pair``, in order); returns results.csv's row of the method."""
    pairs = pd.read_csv(method_outputs.method_dir(output_dir, method) / "pairs.csv")
    assert len(pairs) == len(sequence_pairs)
    assert list(zip(pairs["query"], pairs["reference"], pairs["label"])) == [
        (p.query, p.reference, p.label) for p in sequence_pairs
    ]
    assert ((pairs["num_inliers"] >= 0) & (pairs["num_inliers"] <= pairs["num_matches"])).all()
    row = pd.read_csv(output_dir / "results.csv").set_index("method").loc[method]
    assert row["n_pairs"] == len(pairs) and row["n_positives"] == pairs["label"].sum()
    assert 0 <= row["ap"] <= 1 and 0 <= row["max_recall"] <= 1
    # results.csv keeps 6 significant digits (io_utils.atomic_write_csv)
    expected = metrics.evaluate_scores(pairs["label"].to_numpy(), pairs["score"].to_numpy())
    assert row["ap"] == pytest.approx(expected["ap"], rel=1e-5)
    assert row["max_recall"] == pytest.approx(expected["max_recall"], rel=1e-5)
    stages = pairs["extract_seconds"] + pairs["match_seconds"] + pairs["verify_seconds"]
    assert row["seconds_per_pair"] == pytest.approx(stages.mean(), rel=1e-5)
    return row


def two_view_scene(n_inliers=150, n_outliers=60, seed=0):
    """Points of a non-planar scene seen by two cameras, plus random outlier matches."""
    rng = np.random.default_rng(seed)
    points = np.c_[rng.uniform(-4, 4, n_inliers), rng.uniform(-3, 3, n_inliers), rng.uniform(6, 20, n_inliers)]
    K = np.array([[500.0, 0, 320], [0, 500, 240], [0, 0, 1]])
    angle = np.deg2rad(8)
    R = np.array([[np.cos(angle), 0, np.sin(angle)], [0, 1, 0], [-np.sin(angle), 0, np.cos(angle)]])
    t = np.array([1.0, 0.1, 0.3])
    project = lambda X: (X @ K.T)[:, :2] / (X @ K.T)[:, 2:]
    p0, p1 = project(points), project(points @ R.T + t)
    p0 = p0 + rng.normal(0, 0.3, p0.shape)
    p1 = p1 + rng.normal(0, 0.3, p1.shape)
    return with_outlier_matches(rng, p0, p1, n_outliers)


def papermill_process(cwd: Path, notebook: str | Path, output: Path, *arguments: str) -> subprocess.CompletedProcess:
    """``papermill NOTEBOOK OUTPUT ARGUMENTS`` run in ``cwd`` (one job, one thread), checked to succeed."""
    done = subprocess.run(
        [sys.executable, "-m", "papermill", str(notebook), str(output), *map(str, arguments)],
        capture_output=True,
        text=True,
        timeout=600,
        cwd=cwd,
        env={**os.environ, "PYTHONPATH": str(config.PROJECT_ROOT), "GVBENCH_THREADS": "1", "GVBENCH_JOBS": "1"},
    )
    assert done.returncode == 0, done.stderr[-3000:]
    return done


def papermill_from(cwd: Path, stage: str, output: Path, *arguments: str) -> str:
    """``papermill notebooks/STAGE.ipynb OUTPUT ARGUMENTS`` run in ``cwd``; what the notebook printed."""
    papermill_process(cwd, config.PROJECT_ROOT / "notebooks" / f"{stage}.ipynb", output, *arguments)
    cells = json.loads(output.read_text())["cells"]
    return "".join("".join(o.get("text", "")) for c in cells for o in c.get("outputs", []) if o.get("name") == "stdout")


def tiny_route_run(folder: Path, methods: list[str]) -> Path:
    """``methods`` run on a synthetic route of 6 frames (160x120, 36 pairs, 4 false), each as a notebook
    on its own runs it (a run of its own, on one thread); the params file."""
    params = {
        "sequence": "tiny",
        "pairs_builder": "sample",
        "builder_options": {"n_frames": 6, "image_size": [160, 120]},
        "image_root": str(folder / "data"),
        "pairs": str(folder / "data" / "pairs.txt"),
        "methods": methods,
        "profile": "repository",
        "output_dir": str(folder / "out"),
        "cache_dir": str(folder / "cache"),
        "seed": 0,
    }
    path = folder / "tiny.yaml"
    path.write_text(yaml.safe_dump(params))
    loaded = config.load_params(path) | {"device": "cpu"}
    sequence = sequence_build.prepare_sequence(loaded)
    for method in methods:
        method_runs.run_method_of_params(loaded, sequence, method, progress=False, threads=1)
    return path
