"""`data fetch|list|check`: downloads served by a local HTTP server in a thread (no internet)."""

from __future__ import annotations

import hashlib
import http.server
import os
import subprocess
import sys
import threading
import types
from pathlib import Path

import cv2
import numpy as np
import pooch
import pytest

from gvbench_nb import cli
from gvbench_nb.data import fetch as data
from gvbench_nb.runner import config, sequence_build

PROJECT_ROOT = Path(__file__).resolve().parents[2]


class FileServer:
    """Serves ``files`` (URL path -> bytes) and records every path asked; ``cut_after[path] = n``: the
    first answer for ``path`` announces the whole length but sends ``n`` bytes and closes (a cut download)."""

    def __init__(self) -> None:
        self.files: dict[str, bytes] = {}
        self.cut_after: dict[str, int] = {}
        self.requests: list[str] = []
        server = self

        class Handler(http.server.BaseHTTPRequestHandler):
            def log_message(self, *args) -> None:  # keep pytest's output clean
                pass

            def do_GET(self) -> None:
                server.requests.append(self.path)
                body = server.files.get(self.path)
                if body is None:
                    self.send_error(404, "Not Found")
                    return
                self.send_response(200)
                self.send_header("Content-Length", str(len(body)))
                self.end_headers()
                self.wfile.write(body[: server.cut_after.pop(self.path, len(body))])
                self.close_connection = True

        self.httpd = http.server.ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.url = f"http://127.0.0.1:{self.httpd.server_address[1]}"


@pytest.fixture
def server():
    running = FileServer()
    threading.Thread(target=running.httpd.serve_forever, daemon=True).start()
    yield running
    running.httpd.shutdown()
    running.httpd.server_close()


@pytest.fixture(autouse=True)
def one_attempt(monkeypatch):
    """A failed download is not tried again (pooch waits seconds between tries); the retry test sets its own."""
    monkeypatch.setattr(data, "ATTEMPTS", 1)


def payload(seed: int, size: int) -> bytes:
    return np.random.default_rng(seed).integers(0, 256, size, dtype=np.uint8).tobytes()


def make_dataset(files: dict[str, bytes], base_url: str, wrong_hash: str | None = None) -> data.Dataset:
    entries = tuple(
        data.DataFile(
            path, f"src/{path}", len(body), "0" * 64 if path == wrong_hash else hashlib.sha256(body).hexdigest()
        )
        for path, body in files.items()
    )
    return data.Dataset("toy", "toy", base_url + "/", entries, {})


TOY = {"a/one.bin": payload(1, 300_000), "b/two.bin": payload(2, 5_000), "three.txt": b"query reference 1\n"}


def serve(server: FileServer, files: dict[str, bytes], prefix: str = "/src/") -> None:
    server.files.update({prefix + path: body for path, body in files.items()})


def fetch_toy(root: Path, toy: data.Dataset, mirror: str | None = None) -> dict[str, int]:
    return data.fetch(["toy"], to=root, mirror=mirror, progress=False, datasets={"toy": toy})


def files_under(root: Path) -> list[str]:
    """Every file below ``root``, relative: a download's temporary file would show here."""
    return sorted(p.relative_to(root).as_posix() for p in root.rglob("*") if p.is_file())


def test_download_places_every_file_verified_a_rerun_downloads_nothing_and_a_corrupted_file_again(server, tmp_path):
    serve(server, TOY)
    toy = make_dataset(TOY, server.url)
    assert fetch_toy(tmp_path, toy) == {"toy": 3}
    assert {path: (tmp_path / "toy" / path).read_bytes() for path in TOY} == TOY
    assert sorted(server.requests) == sorted(f"/src/{p}" for p in TOY)
    assert files_under(tmp_path) == sorted(f"toy/{p}" for p in TOY)
    assert fetch_toy(tmp_path, toy) == {"toy": 0}
    assert len(server.requests) == len(TOY)
    (tmp_path / "toy" / "three.txt").write_bytes(b"query reference 0\n")  # corrupted: fetched again
    assert fetch_toy(tmp_path, toy) == {"toy": 1}
    assert (tmp_path / "toy" / "three.txt").read_bytes() == TOY["three.txt"]


def test_a_cut_connection_is_tried_again_and_the_file_arrives_whole(server, tmp_path, monkeypatch):
    monkeypatch.setattr(data, "ATTEMPTS", 2)
    serve(server, TOY)
    server.cut_after["/src/a/one.bin"] = 100_000
    fetch_toy(tmp_path, make_dataset(TOY, server.url))
    assert (tmp_path / "toy" / "a" / "one.bin").read_bytes() == TOY["a/one.bin"]
    assert server.requests.count("/src/a/one.bin") == 2 and files_under(tmp_path) == sorted(f"toy/{p}" for p in TOY)


def test_a_wrong_hash_fails_naming_file_url_and_both_hashes_and_leaves_nothing(server, tmp_path):
    serve(server, TOY)
    with pytest.raises(data.DataError) as raised:
        fetch_toy(tmp_path, make_dataset(TOY, server.url, wrong_hash="b/two.bin"))
    message = str(raised.value)
    assert message.startswith(f"toy: b/two.bin from {server.url}/src/b/two.bin has SHA-256 ")
    assert hashlib.sha256(TOY["b/two.bin"]).hexdigest() in message and "0" * 64 in message and "rerun" in message
    assert files_under(tmp_path) == ["toy/a/one.bin"]


def test_a_missing_file_fails_naming_the_url_and_keeps_only_folders_holding_files(server, tmp_path):
    serve(server, {"a/one.bin": TOY["a/one.bin"]})  # b/two.bin and three.txt: 404
    with pytest.raises(data.DataError) as raised:
        fetch_toy(tmp_path, make_dataset(TOY, server.url))
    message = str(raised.value)
    assert message.startswith(f"toy: b/two.bin: {server.url}/src/b/two.bin answered HTTP 404") and "--mirror" in message
    assert files_under(tmp_path) == ["toy/a/one.bin"] and not (tmp_path / "toy" / "b").exists()


def test_an_unreachable_source_says_so_names_no_file_and_leaves_no_empty_folder(tmp_path):
    root = tmp_path / "data"
    with pytest.raises(data.DataError) as raised:  # the discard port: nothing listens
        fetch_toy(root, make_dataset({"a/x.bin": b"abc"}, "http://127.0.0.1:9"))
    message = str(raised.value)
    assert message.startswith("toy: a/x.bin: cannot reach 127.0.0.1:9 (Connection refused): ")
    assert "unreachable and nothing was downloaded" in message and "--mirror DIR" in message and "toy/" in message
    assert "\n" not in message
    assert not root.exists()  # the data folder this fetch created, and the dataset's folders, are gone


def test_a_mirror_folder_or_url_with_the_data_layout_is_copied_and_checked(server, tmp_path):
    serve(server, TOY, prefix="/mirror/toy/")
    fetch_toy(tmp_path / "url", make_dataset(TOY, "http://127.0.0.1:9"), mirror=server.url + "/mirror/")
    assert sorted(server.requests) == sorted(f"/mirror/toy/{p}" for p in TOY)
    assert (tmp_path / "url" / "toy" / "a" / "one.bin").read_bytes() == TOY["a/one.bin"]
    mirror = tmp_path / "mirror"
    for path, body in TOY.items():
        (mirror / "toy" / path).parent.mkdir(parents=True, exist_ok=True)
        (mirror / "toy" / path).write_bytes(body)
    toy = make_dataset(TOY, "http://127.0.0.1:9")  # never asked: the mirror has every file
    fetch_toy(tmp_path / "data", toy, mirror=str(mirror))
    assert {path: (tmp_path / "data" / "toy" / path).read_bytes() for path in TOY} == TOY
    (mirror / "toy" / "three.txt").unlink()
    (tmp_path / "data" / "toy" / "three.txt").unlink()
    expected = r"three\.txt is missing in the mirror folder \(expected .*mirror/toy/three\.txt\)"
    with pytest.raises(data.DataError, match=expected):
        fetch_toy(tmp_path / "data", toy, mirror=str(mirror))
    (mirror / "toy" / "three.txt").write_bytes(b"changed\n")
    with pytest.raises(data.DataError, match="SHA-256"):
        fetch_toy(tmp_path / "data", toy, mirror=str(mirror))
    assert not (tmp_path / "data" / "toy" / "three.txt").exists()


def test_a_data_folder_that_cannot_be_written_says_where_to_write_instead(server, tmp_path, monkeypatch):
    serve(server, TOY)
    (tmp_path / "file").touch()
    with pytest.raises(data.DataError, match=r"toy: cannot write .*/file/data/toy/a/one\.bin \(not a directory\); set"):
        fetch_toy(tmp_path / "file" / "data", make_dataset(TOY, server.url))

    def refusing(*args, dir=None, **kwargs):  # as a read-only folder answers (also for root)
        raise PermissionError(13, "Permission denied", dir)

    monkeypatch.setattr(pooch.utils, "tempfile", types.SimpleNamespace(NamedTemporaryFile=refusing))
    expected = r"toy: cannot write .*toy/a/one\.bin \(permission denied\); set GVBENCH_DATA or pass --to a writable"
    with pytest.raises(data.DataError, match=expected):
        fetch_toy(tmp_path, make_dataset(TOY, server.url))
    assert server.requests == []  # refused before any download


def test_unknown_and_external_names_say_what_to_do():
    with pytest.raises(data.DataError, match="unknown dataset 'gardens'.*Known: gvbench-lists, gardens_point"):
        data.fetch(["gardens"], progress=False)
    with pytest.raises(data.DataError, match="gvbench-images cannot be fetched .*1drv.ms.*data check"):
        data.fetch(["gvbench-images"], progress=False)


# ------------------------------------------------------------------ manifest --
def test_the_manifest_pins_both_sources_and_lists_every_file():
    datasets, external = data.load_manifest()
    lists, gardens = datasets["gvbench-lists"], datasets["gardens_point"]
    assert (
        lists.base_url
        == "https://raw.githubusercontent.com/jarvisyjw/GV-Bench/11554ccbdd73eb67df622e18f8f2af2be01bf028/"
    )
    assert sorted(f.path for f in lists.files) == sorted(
        [f"{n}.txt" for n in ("day", "night", "season", "weather", "nordland", "uacampus")] + ["LICENSE"]
    )
    assert lists.url(lists.files[0]).startswith(lists.base_url + "dataset/gt/")
    assert gardens.base_url == (
        "https://raw.githubusercontent.com/aghagol/loop-detection/2efbb768787235a4a020d6b27ca0a1761beb515d/"
    )
    for traversal in ("day_left", "day_right", "night_right"):
        frames = sorted(f.path for f in gardens.files if f.path.startswith(traversal + "/"))
        assert frames == [f"{traversal}/Image{i:03d}.jpg" for i in range(200)]
    assert all(f.source == "PR_bench/GardensPointWalking/" + f.path for f in gardens.files)
    assert all(len(f.sha256) == 64 and f.bytes > 0 for d in datasets.values() for f in d.files)
    assert "gvbench-images" in external and "day0" in external["gvbench-images"]["layout"]
    assert "datasets.json" in (PROJECT_ROOT / "pyproject.toml").read_text()  # package data


def test_the_data_folder_is_gvbench_data_else_a_user_cache(monkeypatch, tmp_path):
    monkeypatch.setenv("GVBENCH_DATA", str(tmp_path))
    assert data.data_dir() == tmp_path.resolve() == data.data_dir()
    monkeypatch.delenv("GVBENCH_DATA")
    import platformdirs

    assert data.data_dir() == platformdirs.user_cache_path("gvbench-nb") / "data"


# ----------------------------------------------------------------------- CLI --
def test_data_commands_run_without_importing_torch(tmp_path):
    code = (
        "import sys; from gvbench_nb import cli; status = cli.main(['data', 'list']); "
        "assert status == 0 and 'torch' not in sys.modules, sorted(m for m in sys.modules if 'torch' in m)"
    )
    done = subprocess.run(
        [sys.executable, "-c", code],
        capture_output=True,
        text=True,
        timeout=120,
        env={**os.environ, "PYTHONPATH": str(PROJECT_ROOT), "GVBENCH_DATA": str(tmp_path)},
    )
    assert done.returncode == 0, done.stderr
    assert f"data folder: {tmp_path.resolve()}" in done.stdout
    assert "gardens_point" in done.stdout and "absent" in done.stdout and "1drv.ms" in done.stdout


def test_cli_fetch_exits_2_with_one_sentence_when_a_mirror_serves_other_bytes(server, tmp_path, monkeypatch, capsys):
    datasets, _ = data.load_manifest()
    first = datasets["gvbench-lists"].files[0]
    serve(server, {first.path: payload(3, first.bytes)}, prefix="/gvbench_gt/")
    monkeypatch.setenv("GVBENCH_DATA", str(tmp_path))
    assert cli.main(["data", "fetch", "gvbench-lists", "--mirror", server.url, "--quiet"]) == 2
    printed = capsys.readouterr().err.splitlines()
    assert printed[0] == f"data folder: {tmp_path.resolve()}" and len(printed) == 2
    assert printed[1].startswith(f"error: gvbench-lists: {first.path} from {server.url}/gvbench_gt/{first.path} ")
    assert "SHA-256" in printed[1]
    assert not (tmp_path / "gvbench_gt").exists()  # nothing placed: no folder left either


def gardens_folder(root: Path, frames: int = 12, broken: str | None = None) -> None:
    for traversal in ("day_left", "day_right", "night_right"):
        (root / "gardens_point" / traversal).mkdir(parents=True, exist_ok=True)
        for i in range(frames):
            image = np.full((24, 32, 3), i * 10, np.uint8)
            cv2.imwrite(str(root / "gardens_point" / traversal / f"Image{i:03d}.jpg"), image)
    if broken:
        (root / "gardens_point" / broken).write_bytes(b"not a jpeg")


def test_check_reports_counts_and_first_missing_files_of_a_params(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("GVBENCH_DATA", str(tmp_path / "data"))
    gardens_folder(tmp_path / "data", broken="day_right/Image003.jpg")
    params = PROJECT_ROOT / "params" / "gardens_point.yaml"
    assert cli.main(["data", "check", str(params), "--quiet"]) == 1
    report = capsys.readouterr().out
    assert "24 images named by the folders night_right, day_right" in report
    assert "present 24, decode 23, missing 0, do not decode 1" in report and "day_right/Image003.jpg" in report
    # An official list: the images come from the pair list under --image-root.
    lists = tmp_path / "data" / "gvbench_gt"
    lists.mkdir()
    (lists / "night.txt").write_text(
        "night_right/Image001.jpg day_right/Image001.jpg 1\nnight_right/Image099.jpg day_right/Image002.jpg 0\n"
    )
    night, image_root = str(PROJECT_ROOT / "params" / "night.yaml"), str(tmp_path / "data" / "gardens_point")
    status = cli.main(["data", "check", night, "--quiet", "--image-root", image_root])
    report = capsys.readouterr().out
    assert status == 1 and "4 images named by the pair list" in report
    assert "missing 1" in report and "first missing: night_right/Image099.jpg" in report
    assert "data list` says where to get them (gvbench-images)" in report


def test_check_without_data_names_the_fetch_command(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("GVBENCH_DATA", str(tmp_path))
    assert cli.main(["data", "check", str(PROJECT_ROOT / "params" / "gardens_point_viewpoint.yaml"), "--quiet"]) == 1
    report = capsys.readouterr().out
    assert "data fetch gardens_point" in report
    # Missing folders name no image: counted as folders, not as images.
    assert ": 0 images named by the folders" in report and "present 0, decode 0, missing 0," in report
    assert "missing folders: day_left/, day_right/" in report and "NOT ready to run" in report
    assert cli.main(["data", "check", str(PROJECT_ROOT / "params" / "night.yaml"), "--quiet"]) == 2
    error = capsys.readouterr().err
    assert "image_root is not set; pass --image-root" in error
    status = cli.main(["data", "check", str(PROJECT_ROOT / "params" / "night.yaml"), "--image-root", str(tmp_path)])
    assert status == 2 and "data fetch gvbench-lists" in capsys.readouterr().err


def test_run_without_gardens_point_names_the_fetch_command(tmp_path, monkeypatch):
    monkeypatch.setenv("GVBENCH_DATA", str(tmp_path))
    params = config.load_params(
        PROJECT_ROOT / "params" / "gardens_point.yaml", pairs=str(tmp_path / "p.txt"), output_dir=str(tmp_path / "out")
    )
    with pytest.raises(config.ParamsError, match="data fetch gardens_point"):
        sequence_build.prepare_sequence(params)


@pytest.mark.real_data
def test_the_real_data_folder_matches_the_manifest(shared_data):
    datasets, _ = data.load_manifest()
    for name in ("gvbench-lists", "gardens_point"):
        for item in datasets[name].files[::25]:
            assert pooch.file_hash(str(shared_data / datasets[name].folder / item.path)) == item.sha256, item.path
