"""Atomic file writes: write to a temporary file in the same folder, fsync, then rename.

A crash or a kill in the middle never leaves a truncated map or trajectory behind: readers see
either the old file or the new one.
"""
from __future__ import annotations

import contextlib
import os
import tempfile


@contextlib.contextmanager
def atomic_path(path: str, suffix: str = ""):
    """Yield a temporary path next to ``path``; on success it is renamed onto ``path``."""
    path = os.path.abspath(path)
    d = os.path.dirname(path)
    os.makedirs(d, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix="." + os.path.basename(path) + ".", suffix=suffix or ".tmp",
                               dir=d)
    os.close(fd)
    try:
        yield tmp
        with open(tmp, "rb+") as f:
            os.fsync(f.fileno())
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)


def remove_stale_temporaries(path: str) -> int:
    """Delete the temporary files :func:`atomic_path` left next to ``path`` when a writer was
    killed mid-write (call it before the owner of ``path`` starts writing). Returns how many."""
    path = os.path.abspath(path)
    d, prefix = os.path.dirname(path), "." + os.path.basename(path) + "."
    n = 0
    try:
        names = os.listdir(d)
    except OSError:
        return 0
    for name in names:
        if name.startswith(prefix):
            try:
                os.unlink(os.path.join(d, name))
                n += 1
            except OSError:
                pass
    return n


def atomic_write(path: str, data, mode: str = "wb") -> None:
    """Write ``data`` (bytes or str) to ``path`` atomically."""
    with atomic_path(path) as tmp:
        with open(tmp, mode) as f:
            f.write(data)
