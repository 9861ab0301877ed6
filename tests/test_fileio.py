"""Atomic writes: the old file or the new one, never a torn one; modes as a plain open() gives."""
from __future__ import annotations

import os
import stat

import pytest

from engine.io.fileio import atomic_path, atomic_write


def test_new_file_gets_umask_mode_and_replaced_file_keeps_its_mode(tmp_path):
    mask = os.umask(0o022)
    os.umask(mask)
    new = atomic_write(tmp_path / "a.bin", lambda fh: fh.write(b"one"))
    assert new.read_bytes() == b"one"
    assert stat.S_IMODE(new.stat().st_mode) == 0o666 & ~mask  # not mkstemp's 0600
    os.chmod(new, 0o640)
    atomic_write(new, lambda fh: fh.write(b"two"))
    assert new.read_bytes() == b"two"
    assert stat.S_IMODE(new.stat().st_mode) == 0o640


def test_failed_write_leaves_the_old_file_and_no_temporary(tmp_path):
    target = tmp_path / "keep.txt"
    target.write_bytes(b"old")

    def boom(fh):
        fh.write(b"half")
        raise RuntimeError("killed mid-write")

    with pytest.raises(RuntimeError):
        atomic_write(target, boom)
    assert target.read_bytes() == b"old"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["keep.txt"]
    with pytest.raises(ValueError), atomic_path(target, suffix=".png") as tmp:
        assert tmp.endswith(".png")
        raise ValueError
    assert target.read_bytes() == b"old"
