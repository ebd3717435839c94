"""One digest a kind of input: a retrieval pair file is stale when an image it was built from has other
bytes, by the images' content keys (the feature cache's), whatever the file's size, mtime and inode say."""

from __future__ import annotations

import os

import pytest
from test_input_checks import add_frame, counted_retrieval_builds


@pytest.mark.reliability
def test_a_retrieval_pair_file_is_rebuilt_when_an_image_is_rewritten_in_place(tmp_path, monkeypatch):
    prepare, builds = counted_retrieval_builds(tmp_path, monkeypatch)
    prepare()
    assert len(builds) == 1
    image = tmp_path / "images" / "day" / "Image005.png"
    before, old = image.stat(), image.read_bytes()
    add_frame(tmp_path / "images", tmp_path / "cache", "day", 5, shade=1)  # rewritten in place: other bytes
    os.utime(image, ns=(before.st_atime_ns, before.st_mtime_ns))  # its mtime put back
    after = image.stat()
    assert image.read_bytes() != old
    assert (after.st_size, after.st_mtime_ns, after.st_ino) == (before.st_size, before.st_mtime_ns, before.st_ino)
    prepare()
    assert len(builds) == 2
    prepare()
    assert len(builds) == 2  # unchanged since: not rebuilt
