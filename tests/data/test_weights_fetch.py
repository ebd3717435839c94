"""``python -m gvbench_nb weights fetch``, through local files: small fake checkpoints and hashes of
this test's own making (no official file is needed, and no network)."""

from __future__ import annotations

import dataclasses
import hashlib
import io
import tarfile

import pytest

from gvbench_nb import cli
from gvbench_nb.data import weights_fetch
from gvbench_nb.protocol import weights


def run_cli(capsys, *argv: str) -> tuple[int, str, str]:
    capsys.readouterr()
    code = cli.main(["weights", "fetch", *argv])
    said = capsys.readouterr()
    return code, said.out, said.err.strip().splitlines()[-1] if said.err.strip() else ""


def sha256(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def test_a_file_under_its_url_name_is_saved_under_the_name_the_model_loads(empty_hub, tmp_path, capsys):
    data = b"fake superpoint lightglue"
    (tmp_path / "superpoint_lightglue.pth").write_bytes(data)  # as the release page names it
    code, said, err = run_cli(capsys, "lightglue_superpoint", "--from", str(tmp_path), "--sha256", sha256(data))
    assert code == 0, err
    assert (empty_hub / "superpoint_lightglue_v0-1_arxiv-pth").read_bytes() == data
    assert "licence: Apache-2.0 (LightGlue)" in said and sha256(data) in said
    assert run_cli(capsys, "lightglue_superpoint", "--sha256", sha256(data))[1].count("is there") == 1


@pytest.mark.reliability
def test_a_file_whose_hash_differs_is_refused_and_not_saved(empty_hub, tmp_path, capsys):
    (tmp_path / "superpoint_v1.pth").write_bytes(b"not the file")
    code, _, err = run_cli(capsys, "superpoint_v1", "--from", str(tmp_path), "--sha256", sha256(b"the file"))
    assert code == 2 and f"not {sha256(b'the file')}" in err and "not saved" in err
    assert not (empty_hub / "superpoint_v1.pth").exists() and not list(empty_hub.glob(".*.partial"))


@pytest.mark.reliability
def test_without_a_published_hash_the_first_fetch_records_it_and_later_ones_are_checked(empty_hub, tmp_path, capsys):
    first, second = tmp_path / "first", tmp_path / "second"
    first.mkdir(), second.mkdir()
    (first / "loftr_outdoor.ckpt").write_bytes(b"loftr weights")
    (second / "loftr_outdoor.ckpt").write_bytes(b"other weights")
    code, said, _ = run_cli(capsys, "loftr_outdoor", "--from", str(first))
    assert code == 0 and "no published hash: recorded" in said
    assert weights_fetch.recorded_hashes() == {"loftr_outdoor.ckpt": sha256(b"loftr weights")}
    (empty_hub / "loftr_outdoor.ckpt").unlink()
    code, _, err = run_cli(capsys, "loftr_outdoor", "--from", str(second))
    assert code == 2 and "recorded at its first fetch" in err
    assert not (empty_hub / "loftr_outdoor.ckpt").exists()


def test_a_download_is_checked_and_an_unreachable_source_names_its_url(empty_hub, tmp_path, capsys, monkeypatch):
    data = b"netvlad"
    (tmp_path / "Pitts30K_struct.mat").write_bytes(data)
    checkpoint = weights.get("netvlad_pitts30k")
    local = dataclasses.replace(checkpoint, urls=((tmp_path / "Pitts30K_struct.mat").as_uri(),))
    monkeypatch.setitem(weights.CHECKPOINTS, "netvlad_pitts30k", local)
    code, said, err = run_cli(capsys, "netvlad_pitts30k", "--sha256", sha256(data))
    assert code == 0, err
    assert (empty_hub / "Pitts30K_struct.mat").read_bytes() == data and "MIT (NetVLAD)" in said

    offline = dataclasses.replace(checkpoint, urls=("http://127.0.0.1:9/Pitts30K_struct.mat",))
    monkeypatch.setitem(weights.CHECKPOINTS, "netvlad_pitts30k", offline)
    (empty_hub / "Pitts30K_struct.mat").unlink()
    code, _, err = run_cli(capsys, "netvlad_pitts30k")
    assert code == 2 and "http://127.0.0.1:9/Pitts30K_struct.mat" in err and "--from DIR" in err
    assert not list(empty_hub.glob("*Pitts30K*"))


def test_the_doppelgangers_checkpoint_is_taken_from_its_archive(empty_hub, tmp_path, capsys):
    data = b"doppelgangers classifier"
    with tarfile.open(tmp_path / "checkpoint.tar.gz", "w:gz") as archive:
        member = tarfile.TarInfo("doppelgangers/checkpoints/doppelgangers_classifier_loftr.pt")
        member.size = len(data)
        archive.addfile(member, io.BytesIO(data))
    code, _, err = run_cli(capsys, "doppelgangers_classifier_loftr", "--from", str(tmp_path), "--sha256", sha256(data))
    assert code == 0, err
    assert (empty_hub / "doppelgangers_classifier_loftr.pt").read_bytes() == data


def test_one_hash_for_several_files_is_refused(empty_hub, capsys):
    code, _, err = run_cli(capsys, "superpoint_v1", "loftr_outdoor", "--sha256", sha256(b"x"))
    assert code == 2 and "give one NAME" in err
