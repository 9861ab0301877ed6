"""Atomic file writes: a crash or a kill at any moment leaves the old file or the new one.

Every file the engine writes for the user (checkpoints, run records, spike streams,
images, point clouds) goes through here: the bytes go to a temporary file in the same
folder, then ``os.replace`` swaps it in (atomic on POSIX and Windows).
"""
from __future__ import annotations

import os
import tempfile
from contextlib import contextmanager
from pathlib import Path
from typing import BinaryIO, Callable, Iterator


@contextmanager
def atomic_path(path: str | Path, suffix: str = "") -> Iterator[str]:
    """Yield a temporary filename next to ``path``; on success it replaces ``path``.

    ``suffix`` keeps the extension for writers that pick a format from the name. On any
    error the temporary file is removed and ``path`` is left as it was.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp" + suffix)
    os.close(fd)
    try:
        yield tmp
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def atomic_write(path: str | Path, write: Callable[[BinaryIO], object], *, fsync: bool = True) -> Path:
    """Call ``write(binary_file_handle)`` and swap the result in atomically."""
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as fh:
            write(fh)
            if fsync:  # the data is on disk before the rename makes it visible
                fh.flush()
                os.fsync(fh.fileno())
    return Path(path)
