"""Inputs are checked before any work (a refused run leaves nothing behind), odd paths are named
as what they are, and a full disk or Ctrl-C ends in one sentence. Images: scikit-image's photographs."""

from __future__ import annotations

import json
import math
import os
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
from helpers import PAIRS, assert_nothing_written, cli_error, write_params, write_root

from gvbench_nb import cli
from gvbench_nb.data import build_inputs
from gvbench_nb.data.sequences import MissingImagesError, PairFileError, Sequence, read_pairs, write_pairs
from gvbench_nb.protocol.images import ImageReadError, read_image
from gvbench_nb.runner import config, image_features, input_checks, scoring, sequence_build

pytestmark = pytest.mark.reliability

PROJECT = Path(__file__).resolve().parents[2]


@pytest.fixture
def absent_images(tmp_path) -> Path:
    """Pairs naming absent images: a run past the params checks would stop there, its folders made."""
    (tmp_path / "images").mkdir()
    write_pairs(tmp_path / "pairs.txt", PAIRS)
    return tmp_path


# ----------------------------------------------------------- params in range --
@pytest.mark.parametrize(
    "key, value, expected",
    [
        ("threshold_px", -1, "threshold_px must be a number of pixels above 0, got -1"),
        ("threshold_px", 0, "threshold_px must be a number of pixels above 0, got 0"),
        ("threshold_px", math.nan, "threshold_px must be a number of pixels above 0, got nan"),
        ("threshold_px", "3", "threshold_px must be a number of pixels above 0, got '3'"),
        ("confidence", 5, "confidence must be a number between 0 and 1 (both excluded), got 5"),
        ("confidence", 1, "confidence must be a number between 0 and 1 (both excluded), got 1"),
        ("confidence", 0.0, "confidence must be a number between 0 and 1 (both excluded), got 0.0"),
        ("max_iters", 0, "max_iters must be a whole number from 1 to 2147483647, got 0"),
        ("max_iters", 10.5, "max_iters must be a whole number from 1 to 2147483647, got 10.5"),
        ("max_iters", 2**31, "max_iters must be a whole number from 1 to 2147483647, got 2147483648"),
        ("min_matches", -1, "min_matches must be a whole number of at least 0, got -1"),
        ("resize_to", [0, 288], "resize_to must be [width, height], two whole numbers of at least 1, got [0, 288]"),
    ],
)
def test_verifier_values_out_of_range_are_refused_naming_the_file_and_key(tmp_path, key, value, expected):
    path = write_params(tmp_path, verifier={key: value})
    with pytest.raises(config.ParamsError) as error:
        config.load_params(path)
    assert str(error.value) == f"{path}: verifier: {expected}"


@pytest.mark.parametrize(
    "change, expected",
    [
        ({"seed": -1}, "seed must be an integer of at least 0, got -1"),
        ({"output_dir": "out\0put"}, "output_dir holds a NUL byte"),
    ],
    ids=["seed-numpy-refuses", "nul-byte-in-path"],
)
def test_a_seed_numpy_refuses_or_a_path_with_a_nul_byte_is_refused_naming_the_key(tmp_path, change, expected):
    path = write_params(tmp_path, **change)
    with pytest.raises(config.ParamsError, match=f"{path}: {expected}"):
        config.load_params(path)


def test_a_threshold_of_zero_is_refused_before_any_file_is_written(absent_images, capsys):
    path = write_params(absent_images, verifier={"threshold_px": 0})
    message = cli_error(capsys, "run", str(path))
    assert f"{path}: verifier: threshold_px must be a number of pixels above 0, got 0" in message
    assert_nothing_written(absent_images)


# -------------------------------------------------------------- the device --
def test_a_device_this_torch_or_machine_lacks_is_refused_before_any_work(absent_images, capsys, monkeypatch):
    import torch

    monkeypatch.setattr(torch.version, "cuda", "12.1")
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 1)
    assert input_checks.device_problem("cuda:0") is None
    assert input_checks.device_problem("cuda:1") == "only 1 CUDA device(s) are visible (cuda:0 to cuda:0)"
    monkeypatch.setattr(torch.version, "cuda", None)
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    path = write_params(absent_images, device="cuda")
    message = cli_error(capsys, "run", str(path))
    assert f"{path}: device 'cuda' cannot be used: this torch ({torch.__version__}) is built without CUDA" in message
    assert "set device: auto" in message
    assert_nothing_written(absent_images)


# ------------------------------------------- one sentence, before any folder --
def test_shard_with_merge_is_one_sentence_before_any_folder(tmp_path, root, capsys):
    write_pairs(tmp_path / "pairs.txt", PAIRS)
    message = cli_error(capsys, "run", str(write_params(tmp_path)), "--shard", "0/2", "--merge")
    assert message.startswith("error: choose one of --shard, --merge and --dask, not --shard and --merge")
    assert_nothing_written(tmp_path)


@pytest.mark.parametrize("given", ["absolute", "relative", "option"])
def test_an_image_root_that_is_a_link_loop_is_called_a_loop(tmp_path, root, capsys, monkeypatch, given):
    (tmp_path / "loop").symlink_to(tmp_path / "loop2")
    (tmp_path / "loop2").symlink_to(tmp_path / "loop")
    write_pairs(tmp_path / "pairs.txt", PAIRS)
    monkeypatch.chdir(tmp_path)  # --image-root loop is read from here, image_root: loop from the params' folder
    params = write_params(tmp_path, image_root={"absolute": str(tmp_path / "loop"), "relative": "loop"}.get(given))
    message = cli_error(capsys, "run", str(params), *(["--image-root", "loop"] if given == "option" else []))
    source = "--image-root" if given == "option" else str(params)
    assert message.startswith(f"error: {source}: image_root {tmp_path / 'loop'} is a symbolic link loop")
    assert_nothing_written(tmp_path)


def test_a_run_failing_in_a_fresh_folder_claims_no_previous_results(tmp_path, root, capsys, monkeypatch):
    from gvbench_nb import run_and_publish

    def kernel_dies(name, output_path, parameters):
        raise RuntimeError("the kernel died")

    monkeypatch.setattr(run_and_publish, "execute_notebook", kernel_dies)
    write_pairs(tmp_path / "pairs.txt", PAIRS)
    with pytest.raises(RuntimeError, match="kernel died"):
        cli.main(["run", str(write_params(tmp_path))])
    said = capsys.readouterr().err
    assert "previous" not in said
    assert f"the run did not finish: {tmp_path / 'out'} shows what it showed before; this run's" in said
    assert scoring.methods_with_results(tmp_path / "out") == [] and not (tmp_path / "out" / "results.csv").exists()


# ------------------------------------------------ method names, and how fast --
def answer_in_a_fresh_interpreter(argv: list[str], cwd: Path) -> dict:
    """``cli.main(argv)`` in a new interpreter: its exit code, stderr and the heavy modules it imported."""
    heavy = ("papermill", "torch", "kornia", "nbclient")
    code = (
        "import contextlib, io, json, sys\nfrom gvbench_nb import cli\nerr = io.StringIO()\n"
        f"with contextlib.redirect_stderr(err):\n    rc = cli.main({argv!r})\n"
        f"print(json.dumps({{'rc': rc, 'err': err.getvalue(), 'imported': [m for m in {heavy!r} if m in sys.modules]}}))"
    )
    done = subprocess.run(
        [sys.executable, "-c", code],
        capture_output=True,
        text=True,
        cwd=cwd,
        env={**os.environ, "PYTHONPATH": str(PROJECT)},
        timeout=120,
    )
    assert done.returncode == 0, done.stderr
    return json.loads(done.stdout.strip().splitlines()[-1])


def test_a_method_or_profile_typo_is_blamed_on_where_it_came_from_before_heavy_imports(absent_images, capsys):
    path = write_params(absent_images)
    answer = answer_in_a_fresh_interpreter(["run", str(path), "--methods", "sift-n"], absent_images)
    assert answer["rc"] == 2
    assert answer["err"].startswith("error: --methods: unknown method 'sift-n'. Did you mean 'sift-nn'?")
    assert str(path) not in answer["err"]
    assert answer["imported"] == []  # neither papermill (seconds) nor a model library
    path = write_params(absent_images, methods=["orb-n"])
    answer = answer_in_a_fresh_interpreter(["run", str(path)], absent_images)
    assert answer["rc"] == 2 and answer["imported"] == []
    assert answer["err"].startswith(f"error: {path}: unknown method 'orb-n'. Did you mean 'orb-nn'?")
    message = cli_error(capsys, "run", str(write_params(absent_images)), "--profile", "papr")
    assert message.startswith("error: --profile: unknown profile 'papr'")
    assert_nothing_written(absent_images)


# ------------------------------------------- a retrieval pair file follows its images --
FRAMES, DIM = 12, 16
WORDS = 3.0 * np.random.default_rng(99).normal(size=(4, DIM))


def place_descriptors(frame: int, salt: int = 0) -> np.ndarray:
    """Descriptors of place ``frame`` (VLAD tells places apart by the offsets from 4 shared words)."""
    place = np.random.default_rng(1000 + frame)
    words = np.arange(32) % len(WORDS)
    rows = WORDS[words] + 0.5 * place.normal(size=(len(WORDS), DIM))[words]
    return (rows + 0.02 * np.random.default_rng([frame, salt]).normal(size=rows.shape)).astype(np.float32)


def add_frame(root: Path, cache_dir: Path, folder: str, frame: int, shade: int = 0) -> None:
    """An image file and its local descriptors in the feature cache (so nothing is extracted)."""
    (root / folder).mkdir(parents=True, exist_ok=True)
    name = f"{folder}/Image{frame:03d}.png"
    cv2.imwrite(str(root / name), np.full((8, 8), (40 * frame + shade) % 255, np.uint8))
    options = build_inputs.parse_options({"query_folder": "night", "reference_folders": ["day"]})
    store = image_features.feature_store(cache_dir, sequence_build.local_feature_conf(options, "repository"))
    descriptors = place_descriptors(frame, shade)
    with store.writer() as writer:
        writer.put(
            image_features.image_key(root, name),
            {
                "keypoints": np.zeros((len(descriptors), 2), np.float32),
                "scores": np.ones(len(descriptors), np.float32),
                "descriptors": descriptors,
                "image_size": np.array([8, 8]),
            },
            {"seconds": 0.0},
        )


def retrieval_params(tmp_path: Path) -> Path:
    options = {
        "query_folder": "night",
        "reference_folders": ["day"],
        "descriptor": "vlad",
        "descriptor_options": {"vlad": {"num_words": 4}},
        "top_n": 3,
        "label_rule": "frame_tolerance",
        "label_params": {"k": 1},
    }
    return write_params(
        tmp_path,
        pairs_builder="retrieval",
        builder_options=options,
        profile="repository",
        pairs=str(tmp_path / "p.txt"),
    )


def counted_retrieval_builds(tmp_path: Path, monkeypatch) -> tuple[Any, list[int]]:
    """Night and day folders of ``FRAMES`` frames with a retrieval params file: a call preparing its
    sequence, and the list that grows by one at each build of its pair file."""
    for folder in ("night", "day"):
        for frame in range(FRAMES):
            add_frame(tmp_path / "images", tmp_path / "cache", folder, frame)
    builds: list[int] = []
    build = sequence_build.PAIR_BUILDERS["retrieval"]
    monkeypatch.setitem(sequence_build.PAIR_BUILDERS, "retrieval", lambda params: (builds.append(1), build(params)))
    path = retrieval_params(tmp_path)
    return (lambda: sequence_build.prepare_sequence(config.load_params(path))), builds


def test_a_retrieval_pair_file_is_rebuilt_when_a_frame_is_added_or_replaced(tmp_path, monkeypatch):
    prepare, builds = counted_retrieval_builds(tmp_path, monkeypatch)
    assert len(prepare().pairs) == 3 * FRAMES and len(builds) == 1
    assert len(prepare().pairs) == 3 * FRAMES and len(builds) == 1  # unchanged: not rebuilt
    for folder in ("night", "day"):
        add_frame(tmp_path / "images", tmp_path / "cache", folder, FRAMES)
    pairs = prepare().pairs
    assert len(builds) == 2 and len(pairs) == 3 * (FRAMES + 1)
    assert any(p.query == f"night/Image{FRAMES:03d}.png" for p in pairs)
    assert any(p.reference == f"day/Image{FRAMES:03d}.png" for p in pairs)
    image = tmp_path / "images" / "day" / "Image005.png"
    before = image.stat()
    add_frame(tmp_path / "images", tmp_path / "cache", "day", 5, shade=1)  # other bytes, same name
    os.utime(image, ns=(before.st_atime_ns, before.st_mtime_ns + 1))  # even with a near-identical mtime
    prepare()
    assert len(builds) == 3
    prepare()
    assert len(builds) == 3


# ------------------------------------------------------------- path kinds --
def _broken_link(root: Path) -> None:
    (root / "reference" / "b.png").unlink()
    (root / "reference" / "b.png").symlink_to(root / "nowhere.png")


def _link_loop(root: Path) -> None:
    (root / "reference" / "b.png").unlink()
    (root / "reference" / "b.png").symlink_to(root / "reference" / "c.png")
    (root / "reference" / "c.png").symlink_to(root / "reference" / "b.png")


def _folder(root: Path) -> None:
    (root / "reference" / "b.png").unlink()
    (root / "reference" / "b.png").mkdir()


def _fifo(root: Path) -> None:
    (root / "reference" / "b.png").unlink()
    os.mkfifo(root / "reference" / "b.png")


PATH_KINDS = [
    (_broken_link, "which is a broken symbolic link (to {root}/nowhere.png, which does not exist)"),
    (_link_loop, "which is a symbolic link loop"),
    (_folder, "which is a folder, not a file"),
    (_fifo, "which is a FIFO (named pipe), not a file"),
]


@pytest.mark.parametrize("make, expected", PATH_KINDS, ids=["broken-link", "link-loop", "folder", "fifo"])
def test_an_image_path_is_named_as_what_it_is(root, make, expected):
    make(root)
    sequence = Sequence("s", root, PAIRS, origin={"pairs_file": "pairs.txt"})
    with pytest.raises(MissingImagesError) as error:
        sequence.check_images()
    assert str(error.value).startswith(
        f"1 of 4 images of sequence 's' cannot be read under {root}, first reference/b.png, "
        + expected.format(root=root)
    )
    assert "(pair 1: query/a.png reference/b.png, pairs.txt)" in str(error.value)
    with pytest.raises(ImageReadError, match=expected.split(" (")[0].removeprefix("which ")):
        read_image(root / "reference" / "b.png")  # never opened: a FIFO would block


@pytest.mark.parametrize("make, expected", PATH_KINDS[2:], ids=["folder", "fifo"])
def test_a_run_naming_a_folder_or_fifo_stops_before_any_work(tmp_path, root, capsys, make, expected):
    make(root)
    write_pairs(tmp_path / "pairs.txt", PAIRS)
    message = cli_error(capsys, "run", str(write_params(tmp_path)))
    assert expected in message and "reference/b.png" in message
    assert_nothing_written(tmp_path)


def test_a_nul_byte_in_a_pair_file_is_named_with_file_and_line(tmp_path):
    path = tmp_path / "pairs.txt"
    path.write_bytes(b"query/a.png reference/a.png 1\nquery/a\x00.png reference/b.png 0\n")
    with pytest.raises(PairFileError, match=f"{path}:2: path 'query/a\\\\x00.png' holds a NUL byte"):
        read_pairs(path)


def test_a_pair_file_that_is_a_fifo_is_named_so(tmp_path):
    os.mkfifo(tmp_path / "pairs.txt")
    with pytest.raises(PairFileError, match=r"pair file .*pairs.txt is a FIFO \(named pipe\), not a file"):
        read_pairs(tmp_path / "pairs.txt")


# --------------------------------------------------------------- faults --
def command(argv: list[str], cwd: Path, limit_kb: int | None = None) -> subprocess.CompletedProcess:
    """``python -m gvbench_nb ARGV`` in a subprocess, under ``ulimit -f limit_kb`` (EFBIG, as a full disk)."""
    line = " ".join([sys.executable, "-m", "gvbench_nb", *argv])
    script = f"ulimit -f {limit_kb}; exec {line}" if limit_kb else f"exec {line}"
    environment = {**os.environ, "PYTHONPATH": str(PROJECT), "GVBENCH_THREADS": "1"}
    return subprocess.run(["bash", "-c", script], capture_output=True, text=True, cwd=cwd, env=environment, timeout=300)


def error_lines(stderr: str) -> list[str]:
    """The error lines of stderr, each from its ``error:`` (a progress bar may end without a newline)."""
    lines = stderr.replace("\r", "\n").splitlines()
    return [line[line.index("error:") :] if "error:" in line else line for line in lines if "error" in line.lower()]


@pytest.mark.slow
def test_a_full_disk_is_one_sentence_naming_the_file_and_a_rerun_recovers(tmp_path):
    # 4 photos of 1024x768: a feature shard of about 1.2 MB, above the 1000 KB limit.
    write_root(tmp_path / "images", size=(1024, 768))
    write_pairs(tmp_path / "pairs.txt", PAIRS)
    params = str(write_params(tmp_path))
    full = command(["run", params, "--shard", "0/1"], tmp_path, limit_kb=1000)
    assert full.returncode == 2, full.stderr[-3000:]
    assert "Traceback" not in full.stderr and "HDF5" not in full.stderr
    [line] = error_lines(full.stderr)
    store = tmp_path / "cache" / "features"
    assert line.startswith(f"error: cannot write the shard {store}/") and "(File too large," in line
    assert [p.name for p in store.rglob("*") if p.is_file()] == []  # nothing half-written stays
    rerun = command(["run", params, "--shard", "0/1"], tmp_path)
    assert rerun.returncode == 0, rerun.stderr[-3000:]
    assert len(list(store.rglob("*.h5"))) == 1


@pytest.mark.slow
def test_a_full_disk_while_a_notebook_is_written_names_the_notebook(tmp_path):
    write_root(tmp_path / "images", size=(1024, 768))
    write_pairs(tmp_path / "pairs.txt", PAIRS)
    full = command(["run", str(write_params(tmp_path))], tmp_path, limit_kb=1000)
    assert full.returncode == 2, full.stderr[-3000:]
    assert "Traceback" not in full.stderr
    [line] = error_lines(full.stderr)
    assert line.startswith(f"error: cannot write {tmp_path / 'out'}/") and "(File too large)" in line, line


@pytest.mark.slow
def test_ctrl_c_prints_one_line_saying_how_to_resume_and_a_rerun_finishes(tmp_path, root):
    write_pairs(tmp_path / "pairs.txt", PAIRS)
    params = str(write_params(tmp_path))
    environment = {**os.environ, "PYTHONPATH": str(PROJECT), "GVBENCH_THREADS": "1"}
    process = subprocess.Popen(
        [sys.executable, "-m", "gvbench_nb", "run", params],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        cwd=tmp_path,
        env=environment,
    )
    import psutil

    try:
        assert process.stdout is not None
        while "executing 01_sequence" not in (line := process.stdout.readline()):  # work has started
            assert line, process.stderr.read() if process.stderr else ""
        time.sleep(0.5)
        kernels = psutil.Process(process.pid).children(recursive=True)
        process.send_signal(signal.SIGINT)
        _, stderr = process.communicate(timeout=60)
    finally:
        if process.poll() is None:
            process.kill()
    assert process.returncode == 130
    assert "Traceback" not in stderr and "KeyboardInterrupt" not in stderr
    [line] = [line for line in stderr.splitlines() if "interrupted" in line]
    assert line == (
        "interrupted; what was finished is kept: run the same command to resume: "
        f"{Path(sys.executable).name} -m gvbench_nb run {params}"
    )
    psutil.wait_procs(kernels, timeout=10)
    assert not [k for k in kernels if k.is_running() and k.status() != psutil.STATUS_ZOMBIE]
    rerun = command(["run", params], tmp_path)
    assert rerun.returncode == 0, rerun.stderr[-3000:]
    assert "results table:" in rerun.stdout


def test_frame_tolerance_options_are_checked_before_any_work(absent_images, capsys):
    for folder in ("night", "day"):
        (absent_images / "images" / folder).mkdir()
    path = write_params(absent_images, pairs_builder="frame_tolerance")
    run = lambda **options: cli_error(
        capsys, "run", str(write_params(absent_images, pairs_builder="frame_tolerance", builder_options=options))
    )
    message = run(query_folder="night", reference_folder="day", tolerence=2)
    assert f"{path}: builder_options: unknown option(s) 'tolerence' (did you mean 'tolerance'?)" in message
    assert f"image folder {absent_images / 'images' / 'dya'} not found" in run(
        query_folder="night", reference_folder="dya"
    )
    (absent_images / "images" / "night" / "Image001.png").symlink_to(absent_images / "gone.png")
    (absent_images / "images" / "day" / "Image001.png").write_bytes(b"")
    for folder in ("night", "day"):  # a far frame: each query has a negative too, so AP and MR are defined
        (absent_images / "images" / folder / "Image050.png").write_bytes(b"")
    message = run(query_folder="night", reference_folder="day")
    assert "first night/Image001.png, which is a broken symbolic link" in message
    assert_nothing_written(absent_images)


@pytest.mark.parametrize(
    ("argv", "hint"),
    [
        (["rn", "params/sample.yaml"], "invalid choice: 'rn'; did you mean 'run'?"),
        (["data", "fech", "gardens_point"], "invalid choice: 'fech'; did you mean 'fetch'?"),
        (["build", "p.yaml", "--descriptor", "vald"], "invalid choice: 'vald'; did you mean 'vlad'?"),
    ],
)
def test_a_mistyped_command_or_choice_gets_a_did_you_mean(argv, hint, capsys):
    with pytest.raises(SystemExit) as stopped:
        cli.main(argv)
    assert stopped.value.code == 2 and hint in capsys.readouterr().err
