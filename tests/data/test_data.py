"""`data fetch|list|check`: downloads served by a local HTTP server in a thread (no internet)."""

from __future__ import annotations

import hashlib
import http.server
import os
import subprocess
import sys
import threading
from pathlib import Path

import cv2
import numpy as np
import pytest

from gvbench_nb import cli
from gvbench_nb.data import fetch as data
from gvbench_nb.runner import config

PROJECT_ROOT = Path(__file__).resolve().parents[2]


class FileServer:
    """Serves ``files`` (URL path -> bytes) with HTTP Range support; records every request.

    ``cut_after[path] = n``: the first answer for ``path`` announces the whole length but
    sends only ``n`` bytes, then closes the connection (a cut download).
    ``ignore_range``: answer 200 with the whole file even when a range is asked for.
    """

    def __init__(self) -> None:
        self.files: dict[str, bytes] = {}
        self.cut_after: dict[str, int] = {}
        self.ignore_range = False
        self.requests: list[tuple[str, str | None]] = []
        server = self

        class Handler(http.server.BaseHTTPRequestHandler):
            def log_message(self, *args) -> None:  # keep pytest's output clean
                pass

            def do_GET(self) -> None:
                server.requests.append((self.path, self.headers.get("Range")))
                body = server.files.get(self.path)
                if body is None:
                    self.send_error(404, "Not Found")
                    return
                start = 0
                wanted = self.headers.get("Range")
                if wanted and not server.ignore_range:
                    start = int(wanted.removeprefix("bytes=").split("-")[0])
                    if start >= len(body):
                        self.send_error(416, "Range Not Satisfiable")
                        return
                    self.send_response(206)
                    self.send_header("Content-Range", f"bytes {start}-{len(body) - 1}/{len(body)}")
                else:
                    self.send_response(200)
                part = body[start:]
                self.send_header("Content-Length", str(len(part)))
                self.end_headers()
                cut = server.cut_after.pop(self.path, None)
                self.wfile.write(part if cut is None else part[:cut])
                if cut is not None:
                    self.wfile.flush()
                    self.close_connection = True

        self.httpd = http.server.ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.url = f"http://127.0.0.1:{self.httpd.server_address[1]}"
        self.thread = threading.Thread(target=self.httpd.serve_forever, daemon=True)

    def paths_asked(self) -> list[str]:
        return [path for path, _ in self.requests]


@pytest.fixture
def server():
    running = FileServer()
    running.thread.start()
    yield running
    running.httpd.shutdown()
    running.httpd.server_close()


def payload(seed: int, size: int) -> bytes:
    return np.random.default_rng(seed).integers(0, 256, size, dtype=np.uint8).tobytes()


def make_dataset(
    files: dict[str, bytes], base_url: str, folder: str = "toy", name: str = "toy", wrong_hash: str | None = None
) -> data.Dataset:
    entries = tuple(
        data.DataFile(
            path=path,
            source=f"src/{path}",
            bytes=len(body),
            sha256="0" * 64 if path == wrong_hash else hashlib.sha256(body).hexdigest(),
        )
        for path, body in files.items()
    )
    return data.Dataset(
        name=name,
        folder=folder,
        title="toy",
        what="toy",
        licence="none",
        citation="none",
        homepage=base_url,
        base_url=base_url + "/",
        files=entries,
    )


TOY = {"a/one.bin": payload(1, 300_000), "b/two.bin": payload(2, 5_000), "three.txt": b"query reference 1\n"}


def serve(server: FileServer, files: dict[str, bytes], prefix: str = "/src/") -> None:
    server.files.update({prefix + path: body for path, body in files.items()})


def hidden_partials(root: Path) -> list[Path]:
    return sorted(root.rglob(".*.partial"))


def test_download_places_every_file_verified_and_a_rerun_downloads_nothing(server, tmp_path):
    serve(server, TOY)
    toy = make_dataset(TOY, server.url)
    placed = data.fetch(["toy"], to=tmp_path, progress=False, datasets={"toy": toy})
    assert placed == {"toy": 3}
    for path, body in TOY.items():
        assert (tmp_path / "toy" / path).read_bytes() == body
    assert sorted(server.paths_asked()) == sorted(f"/src/{p}" for p in TOY)
    assert hidden_partials(tmp_path) == []
    asked = len(server.requests)
    assert data.fetch(["toy"], to=tmp_path, progress=False, datasets={"toy": toy}) == {"toy": 0}
    assert len(server.requests) == asked


def test_a_cut_connection_resumes_with_a_range_request(server, tmp_path):
    serve(server, TOY)
    server.cut_after["/src/a/one.bin"] = 100_000
    toy = make_dataset(TOY, server.url)
    data.fetch(["toy"], to=tmp_path, progress=False, datasets={"toy": toy})
    assert (tmp_path / "toy" / "a" / "one.bin").read_bytes() == TOY["a/one.bin"]
    ranges = [r for path, r in server.requests if path == "/src/a/one.bin"]
    assert ranges == [None, "bytes=100000-"]


def test_a_partial_file_left_by_an_earlier_run_is_resumed_not_restarted(server, tmp_path):
    serve(server, TOY)
    toy = make_dataset(TOY, server.url)
    target = tmp_path / "toy" / "a" / "one.bin"
    target.parent.mkdir(parents=True)
    data.partial_path(target).write_bytes(TOY["a/one.bin"][:123_456])
    assert not target.exists()  # a partial file never carries the final name
    data.fetch(["toy"], to=tmp_path, progress=False, datasets={"toy": toy})
    assert target.read_bytes() == TOY["a/one.bin"]
    assert ("/src/a/one.bin", "bytes=123456-") in server.requests
    assert hidden_partials(tmp_path) == []


def test_a_server_that_ignores_the_range_restarts_the_file(server, tmp_path):
    serve(server, TOY)
    server.ignore_range = True
    toy = make_dataset(TOY, server.url)
    target = tmp_path / "toy" / "a" / "one.bin"
    target.parent.mkdir(parents=True)
    data.partial_path(target).write_bytes(TOY["a/one.bin"][:1000])
    data.fetch(["toy"], to=tmp_path, progress=False, datasets={"toy": toy})
    assert target.read_bytes() == TOY["a/one.bin"]


def test_a_wrong_hash_fails_naming_file_and_url_and_leaves_nothing(server, tmp_path):
    serve(server, TOY)
    toy = make_dataset(TOY, server.url, wrong_hash="b/two.bin")
    with pytest.raises(data.DataError) as raised:
        data.fetch(["toy"], to=tmp_path, progress=False, datasets={"toy": toy})
    message = str(raised.value)
    assert "b/two.bin" in message and f"{server.url}/src/b/two.bin" in message and "SHA-256" in message
    assert "rerun" in message
    assert not (tmp_path / "toy" / "b" / "two.bin").exists()
    assert hidden_partials(tmp_path) == []


def test_a_missing_file_fails_naming_the_url_and_what_to_do(server, tmp_path):
    serve(server, {k: v for k, v in TOY.items() if k != "three.txt"})
    toy = make_dataset(TOY, server.url)
    with pytest.raises(data.DataError) as raised:
        data.fetch(["toy"], to=tmp_path, progress=False, datasets={"toy": toy})
    message = str(raised.value)
    assert "three.txt" in message and f"{server.url}/src/three.txt" in message and "HTTP 404" in message
    assert "--mirror" in message
    assert not (tmp_path / "toy" / "three.txt").exists()


def test_an_unreachable_source_says_so_names_no_file_and_leaves_no_empty_folder(tmp_path, monkeypatch):
    monkeypatch.setattr(data, "TIMEOUT_SECONDS", 2.0)
    closed = make_dataset({"a/x.bin": b"abc"}, "http://127.0.0.1:9")  # the discard port: nothing listens
    root = tmp_path / "data"
    with pytest.raises(data.DataError) as raised:
        data.fetch(["toy"], to=root, progress=False, datasets={"toy": closed})
    message = str(raised.value)
    assert message.startswith("toy: a/x.bin: cannot reach 127.0.0.1:9 (")
    assert "unreachable and nothing was downloaded" in message and "--mirror DIR" in message
    assert "toy/" in message and ".partial" not in message and "resume" not in message
    assert "\n" not in message
    assert not root.exists()  # the data folder this fetch created, and the dataset's folders, are gone


def test_an_unreachable_source_keeps_an_earlier_partial_file_and_names_it(tmp_path, monkeypatch):
    monkeypatch.setattr(data, "TIMEOUT_SECONDS", 2.0)
    closed = make_dataset({"x.bin": b"abcdef"}, "http://127.0.0.1:9")
    partial = data.partial_path(tmp_path / "toy" / "x.bin")
    partial.parent.mkdir()
    partial.write_bytes(b"abc")  # what a cut download left
    with pytest.raises(data.DataError, match=r"cannot reach 127\.0\.0\.1:9 .*the 3 bytes an earlier attempt left in"):
        data.fetch(["toy"], to=tmp_path, progress=False, datasets={"toy": closed})
    assert partial.read_bytes() == b"abc"


def test_a_failed_fetch_keeps_folders_that_hold_files_placed_before(server, tmp_path):
    serve(server, {"a/one.bin": TOY["a/one.bin"]})  # b/two.bin and three.txt: 404
    toy = make_dataset(TOY, server.url)
    with pytest.raises(data.DataError, match="HTTP 404"):
        data.fetch(["toy"], to=tmp_path, progress=False, datasets={"toy": toy})
    assert (tmp_path / "toy" / "a" / "one.bin").read_bytes() == TOY["a/one.bin"]
    assert not (tmp_path / "toy" / "b").exists()


def test_a_mirror_folder_with_the_data_layout_is_copied_and_checked(tmp_path):
    mirror = tmp_path / "mirror"
    for path, body in TOY.items():
        (mirror / "toy" / path).parent.mkdir(parents=True, exist_ok=True)
        (mirror / "toy" / path).write_bytes(body)
    toy = make_dataset(TOY, "http://127.0.0.1:9")  # never asked: the mirror has every file
    data.fetch(["toy"], to=tmp_path / "data", mirror=str(mirror), progress=False, datasets={"toy": toy})
    for path, body in TOY.items():
        assert (tmp_path / "data" / "toy" / path).read_bytes() == body
    (mirror / "toy" / "three.txt").unlink()
    (tmp_path / "data" / "toy" / "three.txt").unlink()
    with pytest.raises(
        data.DataError, match=r"three\.txt is missing in the mirror folder \(expected .*mirror/toy/three\.txt\)"
    ):
        data.fetch(["toy"], to=tmp_path / "data", mirror=str(mirror), progress=False, datasets={"toy": toy})
    (mirror / "toy" / "three.txt").write_bytes(b"changed\n")
    with pytest.raises(data.DataError, match="SHA-256"):
        data.fetch(["toy"], to=tmp_path / "data", mirror=str(mirror), progress=False, datasets={"toy": toy})
    assert not (tmp_path / "data" / "toy" / "three.txt").exists()


def test_a_mirror_url_is_asked_for_the_data_layout(server, tmp_path):
    serve(server, TOY, prefix="/mirror/toy/")
    toy = make_dataset(TOY, "http://127.0.0.1:9")
    data.fetch(["toy"], to=tmp_path, mirror=server.url + "/mirror/", progress=False, datasets={"toy": toy})
    assert sorted(server.paths_asked()) == sorted(f"/mirror/toy/{p}" for p in TOY)
    assert (tmp_path / "toy" / "a" / "one.bin").read_bytes() == TOY["a/one.bin"]


def test_a_corrupted_file_in_the_data_folder_is_fetched_again(server, tmp_path):
    serve(server, TOY)
    toy = make_dataset(TOY, server.url)
    data.fetch(["toy"], to=tmp_path, progress=False, datasets={"toy": toy})
    (tmp_path / "toy" / "three.txt").write_bytes(b"query reference 0\n")
    assert data.fetch(["toy"], to=tmp_path, progress=False, datasets={"toy": toy}) == {"toy": 1}
    assert (tmp_path / "toy" / "three.txt").read_bytes() == TOY["three.txt"]


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
    assert "gvbench-images" in external and "day0" in external["gvbench-images"].layout


def test_the_manifest_is_package_data():
    text = (PROJECT_ROOT / "pyproject.toml").read_text()
    assert "datasets.json" in text


def test_the_data_folder_is_gvbench_data_else_a_user_cache(monkeypatch, tmp_path):
    monkeypatch.setenv("GVBENCH_DATA", str(tmp_path))
    assert data.data_dir() == tmp_path.resolve() == config.data_dir()
    monkeypatch.delenv("GVBENCH_DATA")
    import platformdirs

    assert data.data_dir() == platformdirs.user_cache_path("gvbench-nb") / "data"


# ----------------------------------------------------------------------- CLI --
def run_cli(*argv: str, env: dict[str, str]) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "gvbench_nb", *argv],
        capture_output=True,
        text=True,
        env={**os.environ, "PYTHONPATH": str(PROJECT_ROOT), **env},
        cwd=PROJECT_ROOT,
        timeout=120,
    )


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
    status = cli.main(
        [
            "data",
            "check",
            str(PROJECT_ROOT / "params" / "night.yaml"),
            "--quiet",
            "--image-root",
            str(tmp_path / "data" / "gardens_point"),
        ]
    )
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
        config.prepare_sequence(params)


@pytest.mark.real_data
def test_the_real_data_folder_matches_the_manifest(shared_data):
    datasets, _ = data.load_manifest()
    for name in ("gvbench-lists", "gardens_point"):
        for item in datasets[name].files[::25]:
            assert data.is_verified(shared_data / datasets[name].folder / item.path, item), item.path


def test_a_data_folder_that_cannot_be_written_says_where_to_write_instead(server, tmp_path, monkeypatch):
    serve(server, TOY)
    toy = make_dataset(TOY, server.url)

    def refusing_open(path, mode="r", *args, **kwargs):  # as a read-only folder answers (also for root)
        if "w" in mode or "a" in mode:
            raise PermissionError(13, "Permission denied", str(path))
        return open(path, mode, *args, **kwargs)

    monkeypatch.setattr(data, "open", refusing_open, raising=False)
    with pytest.raises(
        data.DataError,
        match=r"toy: cannot write .*one\.bin\.partial \(permission denied\); "
        "set GVBENCH_DATA or pass --to a writable folder",
    ):
        data.fetch(["toy"], to=tmp_path, progress=False, datasets={"toy": toy})
    assert len(server.requests) == 1  # not retried
