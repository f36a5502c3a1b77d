"""zoo.files: atomic writes give the file the mode the user's umask says, like open() would."""

from __future__ import annotations

import os
import stat

import pytest

from zoo.files import atomic_path, atomic_write_text, current_umask, write_checksums


@pytest.fixture
def umask():
    old = os.umask(0o022)
    yield lambda mask: os.umask(mask)
    os.umask(old)


@pytest.mark.parametrize("mask", [0o022, 0o027, 0o077, 0o002])
def test_atomic_writes_follow_the_umask(umask, mask, tmp_path):
    umask(mask)
    assert current_umask() == mask
    atomic_write_text(tmp_path / "a.txt", "a")
    with atomic_path(tmp_path / "b.bin") as tmp:
        tmp.write_bytes(b"b")
    write_checksums(tmp_path)
    with open(tmp_path / "plain", "w") as f:  # what open() gives under the same umask
        f.write("c")
    expected = stat.S_IMODE((tmp_path / "plain").stat().st_mode)
    assert expected == 0o666 & ~mask
    for name in ("a.txt", "b.bin", "SHA256SUMS"):
        assert oct(stat.S_IMODE((tmp_path / name).stat().st_mode)) == oct(expected), name
