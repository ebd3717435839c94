"""Bad input gets a clear error naming the file and what to do; nothing a pair file, params file
or checkpoint holds is ever executed."""

from __future__ import annotations

import ast
import os
import re
import struct
import zlib
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from helpers import PAIRS, assert_nothing_written, cli_error, truncated, write_params, write_root

import gvbench_nb
from gvbench_nb.data.sequences import Pair, PairFileError, format_pairs, parse_pairs, read_pairs, write_pairs
from gvbench_nb.protocol import weights
from gvbench_nb.protocol.images import ImageReadError, read_image
from gvbench_nb.runner import config

pytestmark = pytest.mark.reliability

PACKAGE_DIR = Path(gvbench_nb.__file__).resolve().parent


# -------------------------------------------------------- 1. bad input, clear error --
@pytest.mark.parametrize(
    "kind, what",
    [
        ("missing", "not found"),
        ("empty", "empty"),
        ("truncated_jpeg", "truncated"),
        ("truncated_png", "truncated"),
        ("text_as_jpg", "<html>"),
        ("folder", "folder"),
    ],
)
def test_unreadable_images_raise_an_error_naming_the_file(tmp_path, kind, what):
    real = tmp_path / "real.jpg"
    cv2.imwrite(str(real), np.random.default_rng(0).integers(0, 256, (90, 160, 3), dtype=np.uint8))
    path = tmp_path / ("bad.png" if kind == "truncated_png" else "bad.jpg")
    if kind == "empty":
        path.write_bytes(b"")
    elif kind == "truncated_jpeg":
        truncated(real, path)
    elif kind == "truncated_png":
        cv2.imwrite(str(tmp_path / "whole.png"), cv2.imread(str(real)))
        truncated(tmp_path / "whole.png", path)
    elif kind == "text_as_jpg":
        path.write_text("<html>404 Not Found</html>\n")
    elif kind == "folder":
        path.mkdir()
    with pytest.raises(ImageReadError) as error:
        read_image(path)
    message = str(error.value)
    assert str(path) in message and what in message
    assert "image_root" in message or "remove the pairs" in message  # what to do


def _write_png(path: Path, array: np.ndarray) -> Path:
    assert cv2.imwrite(str(path), array)
    return path


def test_uncommon_image_kinds_are_read_not_rejected(tmp_path):
    from PIL import Image

    rng = np.random.default_rng(3)
    rgb = rng.integers(0, 256, (11, 13, 3), dtype=np.uint8)
    gray = rng.integers(0, 256, (11, 13), dtype=np.uint8)
    bgr = rgb[..., ::-1]

    sixteen_rgb = read_image(_write_png(tmp_path / "rgb16.png", bgr.astype(np.uint16) * 257))
    np.testing.assert_array_equal(sixteen_rgb, rgb)
    sixteen_gray = read_image(_write_png(tmp_path / "gray16.png", gray.astype(np.uint16) * 257), grayscale=True)
    np.testing.assert_array_equal(sixteen_gray, gray)
    rgba = read_image(_write_png(tmp_path / "rgba.png", np.dstack([bgr, gray])))
    np.testing.assert_array_equal(rgba, rgb)  # alpha dropped, colours kept
    gray_png = _write_png(tmp_path / "gray.png", gray)
    np.testing.assert_array_equal(read_image(gray_png, grayscale=True), gray)
    np.testing.assert_array_equal(read_image(gray_png), np.dstack([gray] * 3))

    palette = Image.fromarray(rgb).convert("P", palette=Image.ADAPTIVE, colors=8)
    palette.save(tmp_path / "palette.png")
    palette.save(tmp_path / "palette_transparent.png", transparency=0)
    expected = np.asarray(palette.convert("RGB"))
    np.testing.assert_array_equal(read_image(tmp_path / "palette.png"), expected)
    np.testing.assert_array_equal(read_image(tmp_path / "palette_transparent.png"), expected)

    # JPEG is lossy: a flat grey image survives exactly, and the shape must be right.
    flat = np.full((16, 24), 77, dtype=np.uint8)
    Image.fromarray(flat, "L").save(tmp_path / "gray.jpg", quality=100)
    assert read_image(tmp_path / "gray.jpg", grayscale=True).shape == (16, 24)
    np.testing.assert_allclose(read_image(tmp_path / "gray.jpg").astype(int), 77, atol=1)
    assert read_image(tmp_path / "gray.jpg").shape == (16, 24, 3)


@pytest.mark.parametrize("width, height", [(1, 1), (2, 1)], ids=["1x1", "2x1"])
def test_an_image_too_small_to_shrink_is_one_sentence_before_any_folder(tmp_path, capsys, width, height):
    """OpenCV decodes it, but its eighth-size check decode and the extractors cannot shrink it."""
    tiny = write_root(tmp_path / "images") / "tiny.png"
    cv2.imwrite(str(tiny), np.full((height, width, 3), 128, np.uint8))
    write_pairs(tmp_path / "pairs.txt", [*PAIRS, Pair("tiny.png", "reference/a.png", 0)])
    message = cli_error(capsys, "run", str(write_params(tmp_path)))
    assert f"image {tiny} is {width} x {height} pixels, too small to verify" in message
    assert "(pair 4: tiny.png reference/a.png)" in message
    assert_nothing_written(tmp_path)


@pytest.mark.parametrize(
    "lines, limit, expected",
    [
        (["query/a.png reference/a.png 1"] * 2, None, "pairs.txt:2: duplicate pair query/a.png reference/a.png"),
        (["query/a.png reference/a.png 1", "query/b.png reference/b.png 1"], None, "2 pairs with no negatives"),
        (["query/a.png reference/b.png 0", "query/b.png reference/b.png 0"], None, "2 pairs with no positives"),
        (["query/a.png reference/a.png 1", "query/a.png reference/b.png 0"], "1", "first 1 pairs, the limit)"),
    ],
    ids=["repeated-pair", "no-negative", "no-positive", "no-negative-within-the-limit"],
)
def test_what_the_pair_file_alone_decides_is_reported_before_any_image_is_decoded(
    tmp_path, capsys, lines, limit, expected
):
    truncated(write_root(tmp_path / "images") / "reference" / "a.png", tmp_path / "images" / "reference" / "a.png")
    (tmp_path / "pairs.txt").write_text("\n".join(lines) + "\n")
    message = cli_error(capsys, "run", str(write_params(tmp_path)), *(["--limit", limit] if limit else []))
    assert expected in message and "cannot decode" not in message  # not the broken image
    if "duplicate" not in expected:
        assert "AP and MR are undefined; use pairs with both true and false loop closures" in message
    assert_nothing_written(tmp_path)


@pytest.mark.parametrize(
    "lines, message",
    [
        (["ok.png ok2.png 1", "C:\\data\\a.png b.png 1"], "absolute path"),
        (["ok.png ok2.png 1", "C:/data/a.png b.png 1"], "absolute path"),
        (["ok.png ok2.png 1", "\\\\server\\share\\a.png b.png 1"], "absolute path"),
        (["ok.png ok2.png 1", "a.png \\etc\\passwd 1"], "absolute path"),
        (["ok.png ok2.png 1", "..\\a.png b.png 1"], "escapes the image root"),
        (["ok.png ok2.png 1", "a.png day\\..\\..\\b.png 1"], "escapes the image root"),
        (["ok.png ok2.png 1", "a.png b.png 1.0"], "label must be 0 or 1"),
        (["ok.png ok2.png 1", "a.png b.png -1"], "label must be 0 or 1"),
        (
            ["night/./a.jpg day/b.jpg 1", "night//a.jpg day/b.jpg 0"],
            "duplicate pair night/a.jpg day/b.jpg (first on line 1, with the opposite label: 1 there, 0 here)",
        ),
        (
            ["night/a.jpg day/b.jpg 1", "night/a.jpg day/./b.jpg 1"],
            "duplicate pair night/a.jpg day/b.jpg (first on line 1)",
        ),
        (["night/a.jpg day/b.jpg 1", "day/b.jpg night/a.jpg 1"], "(first on line 1, in the other order)"),
        (["night/a.jpg night/a.jpg 1"], "self-pair: query and reference are both"),
        (["night/a.jpg night/./a.jpg 0"], "self-pair: query and reference are both"),
        (["a.jpg ./a.jpg 1"], "self-pair: query and reference are both"),
    ],
)
def test_a_bad_pair_line_is_refused_with_file_and_line(lines, message):
    """Absolute paths, ``..``, Windows-style escapes, odd labels, a pair spelled twice, a self-pair."""
    with pytest.raises(PairFileError) as error:
        parse_pairs(lines, source="pairs.txt")
    assert str(error.value).startswith(f"pairs.txt:{len(lines)}: ") and message in str(error.value)


def test_crlf_bom_and_tabs_are_accepted_and_line_numbers_stay_right(tmp_path):
    path = tmp_path / "pairs.txt"
    path.write_bytes(b"\xef\xbb\xbfnight/a.png day/b.png 1\r\n# comment\r\nnight/a.png\tday/c.png 0\r\n\r\n")
    assert read_pairs(path) == [Pair("night/a.png", "day/b.png", 1), Pair("night/a.png", "day/c.png", 0)]
    path.write_bytes(b"a.png b.png 1\r\nc.png d.png 2\r\n")
    with pytest.raises(PairFileError, match=re.escape(f"{path}:2: label must be 0 or 1, got '2'")):
        read_pairs(path)
    path.write_bytes(b"a.png b.png 1\n\xff\xfe\x00binary\n")
    with pytest.raises(PairFileError, match=re.escape(f"{path}:2: not UTF-8 text")):
        read_pairs(path)


def _params_file(tmp_path: Path, **changes) -> Path:
    params = {
        "sequence": "x",
        "pairs": "p.txt",
        "image_root": ".",
        "methods": ["sift-nn"],
        "profile": "paper",
        "output_dir": "o",
    }
    params.update(changes)
    params = {k: v for k, v in params.items() if v is not None}
    path = tmp_path / "params.yaml"
    import yaml

    path.write_text(yaml.safe_dump(params))
    return path


@pytest.mark.parametrize(
    "changes, expected",
    [
        ({"seeed": 1}, ["unknown key(s) 'seeed' (did you mean 'seed'?)", "Valid keys: sequence, pairs"]),
        ({"output_dir": None}, ["missing key(s) output_dir", "Required keys: sequence, pairs, image_root"]),
        ({"methods": ["sift-nn", "sift_nn2"]}, ["unknown method 'sift_nn2'", "Known: sift-nn, sp-nn"]),
        ({"methods": "sift-nn,disk-lgg"}, ["unknown method 'disk-lgg'. Did you mean 'disk-lg'?"]),
        ({"profile": "fastest"}, ["unknown profile 'fastest'", "Known: paper, repository"]),
        ({"methods": []}, ["methods is empty"]),
        ({"seed": "zero"}, ["seed must be an integer, got 'zero'"]),
        ({"limit": True}, ["limit must be a positive integer or null, got True"]),
        ({"limit": 0}, ["limit must be a positive integer or null, got 0"]),
        ({"device": "gpu"}, ["device must be 'auto', 'cpu', 'cuda', 'cuda:N' or 'mps', got 'gpu'"]),
        ({"builder_options": [1, 2]}, ["builder_options must be a mapping"]),
        ({"pairs_builder": "magic"}, ["unknown pairs_builder 'magic'.", "Known: sample, frame_tolerance"]),
    ],
)
def test_bad_params_name_the_file_and_the_valid_choices(tmp_path, changes, expected):
    path = _params_file(tmp_path, **changes)
    with pytest.raises(config.ParamsError) as error:
        config.load_params(path)
    message = str(error.value)
    assert message.startswith(str(path))
    for part in expected:
        assert part in message


def test_params_yaml_tags_are_not_executed(tmp_path):
    path = tmp_path / "params.yaml"
    path.write_text("sequence: !!python/object/apply:os.system ['touch pwned']\npairs: p\n")
    with pytest.raises(config.ParamsError, match="not valid YAML"):
        config.load_params(path)
    assert not (tmp_path / "pwned").exists() and not Path("pwned").exists()


def test_a_wrong_weights_layout_names_missing_unexpected_and_mis_shaped_tensors():
    module = torch.nn.Sequential(torch.nn.Conv2d(1, 4, 3), torch.nn.ReLU(), torch.nn.Conv2d(4, 2, 1))
    state = module.state_dict()
    state.pop("2.bias")
    state["head.weight"] = torch.zeros(1)
    state["0.weight"] = torch.zeros(4, 1, 5, 5)
    with pytest.raises(weights.WeightsLayoutError) as error:
        weights.load_state_dict_strict(module, state, "model.pth")
    message = str(error.value)
    assert "model.pth: wrong layout for Sequential" in message
    assert "missing tensors: 2.bias" in message
    assert "unexpected tensors: head.weight" in message
    assert "0.weight: file (4, 1, 5, 5) vs model (4, 1, 3, 3)" in message


@pytest.mark.parametrize("content", ["garbage", "truncated", "html"])
def test_a_file_that_is_not_a_checkpoint_is_refused_naming_it(tmp_path, content):
    path = tmp_path / "superpoint_v1.pth"
    if content == "garbage":
        path.write_bytes(np.random.default_rng(0).integers(0, 256, 4096, dtype=np.uint8).tobytes())
    elif content == "truncated":
        torch.save({"w": torch.zeros(1000)}, path)
        path.write_bytes(path.read_bytes()[:2000])
    else:
        path.write_text("<!DOCTYPE html><html>rate limited</html>")
    with pytest.raises(weights.CheckpointReadError) as error:
        weights.load_checkpoint(path)
    assert str(path) in str(error.value) and "Download it again" in str(error.value)
    with pytest.raises(weights.MissingWeightsError, match="checkpoint not found"):
        weights.load_checkpoint(tmp_path / "absent.pth")


# ------------------------------------------------------------------ 5. safety --
@pytest.mark.parametrize("layout", ["zip", "legacy_pickle"])
def test_a_malicious_checkpoint_is_refused_without_running_its_payload(tmp_path, layout):
    marker = tmp_path / "payload_ran"

    class Payload:
        def __reduce__(self):
            return (os.system, (f"touch {marker}",))

    path = tmp_path / "evil.pth"
    if layout == "zip":
        torch.save({"weight": torch.zeros(2), "extra": Payload()}, path)
    else:
        import pickle

        path.write_bytes(pickle.dumps({"extra": Payload()}, protocol=2))
    with pytest.raises(weights.CheckpointReadError) as error:
        weights.load_checkpoint(path)
    assert str(path) in str(error.value)
    assert not marker.exists()


UNSAFE_CALLS = {
    "eval",
    "exec",
    "compile",
    "os.system",
    "os.popen",
    "yaml.load",
    "yaml.unsafe_load",
    "pickle.load",
    "pickle.loads",
    "marshal.loads",
    "subprocess.run",
    "subprocess.call",
    "subprocess.check_call",
    "subprocess.check_output",
    "subprocess.Popen",
}
UNSAFE_MODULES = {"pickle", "marshal", "shelve", "subprocess"}


def _dotted(node: ast.AST) -> str:
    if isinstance(node, ast.Name):
        return node.id
    if isinstance(node, ast.Attribute):
        return f"{_dotted(node.value)}.{node.attr}"
    return ""


def _is_constant(node: ast.AST, value: object) -> bool:
    return isinstance(node, ast.Constant) and node.value is value


def unsafe_code(source: str) -> list[str]:
    """Calls and imports in code (not docstrings or comments) that could run what a
    pair file, params file or checkpoint holds."""
    found = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Call):
            name = _dotted(node.func)
            if name in UNSAFE_CALLS:
                found.append(f"{node.lineno}: {name}(")
            if any(k.arg == "shell" and not _is_constant(k.value, False) for k in node.keywords):
                found.append(f"{node.lineno}: shell=True")
            if name == "torch.load" and not any(
                k.arg == "weights_only" and _is_constant(k.value, True) for k in node.keywords
            ):
                found.append(f"{node.lineno}: torch.load without weights_only=True")
        elif isinstance(node, (ast.Import, ast.ImportFrom)):
            modules = [a.name for a in node.names] if isinstance(node, ast.Import) else [node.module or ""]
            imported = [f"{node.module}.{a.name}" for a in node.names] if isinstance(node, ast.ImportFrom) else []
            if any(m.split(".")[0] in UNSAFE_MODULES for m in modules) or set(imported) & UNSAFE_CALLS:
                found.append(f"{node.lineno}: import {', '.join(modules + imported)}")
    return sorted(found, key=lambda hit: int(hit.split(":")[0]))


def test_the_package_has_no_code_execution_paths():
    hits = [
        f"{source.relative_to(PACKAGE_DIR.parent)}:{hit}"
        for source in sorted(PACKAGE_DIR.rglob("*.py"))
        for hit in unsafe_code(source.read_text(encoding="utf-8"))
    ]
    # The one pickle reader: an Unpickler whose find_class admits numpy's array and scalar builders
    # only (tests/runner/test_score_files.py feeds it a file whose pickle would run code).
    restricted = [
        h for h in hits if h.startswith("gvbench_nb/runner/score_files.py:") and h.endswith(": import pickle")
    ]
    assert len(restricted) == 1 and [h for h in hits if h not in restricted] == []
    assert "find_class" in (PACKAGE_DIR / "runner" / "score_files.py").read_text(encoding="utf-8")
    # A plain-text grep agrees (docstrings may mention eval() of modules, hence the lookbehind).
    for source in PACKAGE_DIR.rglob("*.py"):
        text = source.read_text(encoding="utf-8")
        assert not re.search(r"shell\s*=\s*True|os\.system|yaml\.load\(|(?<![\w.`])(eval|exec)\(", text), source
    # The checker finds what it looks for (so this test can fail).
    bad = (
        "import subprocess\nfrom os import system\nx = eval(s)\nsubprocess.run(c, shell=True)\n"
        "torch.load(p)\nyaml.load(f)\nmodel.eval()\n"
    )
    assert [hit.split(": ", 1)[1] for hit in unsafe_code(bad)] == [
        "import subprocess",
        "import os, os.system",
        "eval(",
        "subprocess.run(",
        "shell=True",
        "torch.load without weights_only=True",
        "yaml.load(",
    ]


def test_paths_are_stored_normalised():
    assert parse_pairs(["night/./a.jpg day//b.jpg 1"]) == [Pair("night/a.jpg", "day/b.jpg", 1)]


def test_names_with_spaces_are_written_in_quotes_and_read_back(tmp_path):
    pairs = [Pair("day 1/a b.jpg", "night/it's.jpg", 1), Pair("plain/a.jpg", 'odd/"q".jpg', 0)]
    path = write_pairs(tmp_path / "pairs.txt", pairs)
    assert read_pairs(path) == pairs
    assert format_pairs([Pair("plain/a.jpg", "plain/b.jpg", 1)]) == "plain/a.jpg plain/b.jpg 1\n"
    assert parse_pairs(["\"day 1/a.jpg\" 'day 2/b.jpg' 1"]) == [Pair("day 1/a.jpg", "day 2/b.jpg", 1)]
    with pytest.raises(
        PairFileError, match=r'pairs.txt:1: expected 3 fields .* got 4: .*in quotes, e.g. "day 1/a.jpg"'
    ):
        parse_pairs(["day 1/a.jpg day/b.jpg 1"], source="pairs.txt")
    with pytest.raises(PairFileError, match=r"No closing quotation .*close the quote"):
        parse_pairs(['"day 1/a.jpg day/b.jpg 1'], source="pairs.txt")


def test_a_megabyte_path_is_reported_by_file_and_line_and_shortened(tmp_path):
    path = tmp_path / "pairs.txt"
    path.write_text("query/a.png reference/a.png 1\n" + "x" * 1_000_000 + " reference/b.png 0\n")
    with pytest.raises(PairFileError) as error:
        read_pairs(path)
    assert str(error.value).startswith(f"{path}:2: path 'xxx") and len(str(error.value)) < 400
    assert "(1000000 characters)" in str(error.value)


def _png_header_only(path: Path, width: int, height: int) -> Path:
    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    header = struct.pack(">IIBBBBB", width, height, 8, 0, 0, 0, 0)  # 8-bit grayscale
    path.write_bytes(
        b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", header) + chunk(b"IDAT", zlib.compress(b"\0" * 64)) + chunk(b"IEND", b"")
    )
    return path


def test_an_image_beyond_the_pixel_bound_is_refused_before_decoding(tmp_path, monkeypatch):
    huge = _png_header_only(tmp_path / "huge.png", 40000, 40000)  # 1.6 gigapixels in 100 bytes
    with pytest.raises(ImageReadError) as error:
        read_image(huge)
    assert f"image {huge} has 1,600,000,000 pixels, above the bound of 64,000,000 pixels" in str(error.value)
    assert "refused before decoding" in str(error.value)
    assert "GVBENCH_MAX_PIXELS" in str(error.value)
    monkeypatch.setenv("GVBENCH_MAX_PIXELS", "1000")
    small = tmp_path / "small.png"
    cv2.imwrite(str(small), np.zeros((40, 40), np.uint8))
    with pytest.raises(ImageReadError, match="40 x 40 = 1,600 pixels, above the bound of 1,000"):
        read_image(small)


def test_a_pickled_checkpoint_for_a_kornia_model_is_refused_before_kornia_loads_it(empty_hub):
    import pickle

    empty_hub.mkdir(parents=True)
    target = weights.checkpoint_path("disk_depth")
    target.write_bytes(pickle.dumps({"extra": os.getcwd}, protocol=2))  # a global: weights_only refuses it
    with pytest.raises(weights.CheckpointReadError) as error:
        weights.require("disk_depth")
    message = str(error.value)
    assert str(target) in message and "Download it again" in message and "weights_only=False" not in message
