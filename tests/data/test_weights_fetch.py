"""``python -m gvbench_nb weights fetch``, through local files: small fake checkpoints and hashes of
this test's own making (no official file is needed, and no network)."""

from __future__ import annotations

import dataclasses
import hashlib
import io
import tarfile

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
    (tmp_path / "superpoint_v1.pth").write_bytes(b"not the file")
    with pytest.raises(fetch.DataError, match=f"not {sha256(b'the file')} .*not saved"):
        weights_fetch.fetch_checkpoint("superpoint_v1", tmp_path, sha256(b"the file"))
    assert list(empty_hub.iterdir()) == []


@pytest.mark.reliability
def test_without_a_published_hash_the_first_fetch_records_it_and_later_ones_are_checked(empty_hub, tmp_path):
    (tmp_path / "loftr_outdoor.ckpt").write_bytes(b"loftr weights")
    assert "no published hash: recorded" in weights_fetch.fetch_checkpoint("loftr_outdoor", tmp_path)
    assert weights_fetch.recorded_hashes() == {"loftr_outdoor.ckpt": sha256(b"loftr weights")}
    (empty_hub / "loftr_outdoor.ckpt").unlink()
    (tmp_path / "loftr_outdoor.ckpt").write_bytes(b"other weights")
    with pytest.raises(fetch.DataError, match="recorded at its first fetch"):
        weights_fetch.fetch_checkpoint("loftr_outdoor", tmp_path)
    assert not (empty_hub / "loftr_outdoor.ckpt").exists()


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


def test_one_hash_for_several_files_is_refused(empty_hub, capsys):
    assert cli.main(["weights", "fetch", "superpoint_v1", "loftr_outdoor", "--sha256", sha256(b"x")]) == 2
    assert capsys.readouterr().err.strip().splitlines()[-1].endswith("give one NAME with it (or run one fetch a NAME)")
