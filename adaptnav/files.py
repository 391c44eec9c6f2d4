"""Atomic file writes, for what must never be left half-written by a crash or a power cut:
the service's learned state (:mod:`adaptnav.service.runtime.persistence`) and the compiled
kernels' specs (:mod:`adaptnav.kernels`, below every layer, so it is here and not in the
service)."""
from __future__ import annotations

import os
import tempfile
from pathlib import Path


def atomic_write_bytes(path: str | Path, data: bytes, mode: int | None = None) -> None:
    """Write ``data`` to ``path`` atomically (tmp + fsync + rename + dir fsync): a crash leaves
    the old file or the new one, never a torn one; ``mode``: the file's permissions (else the
    temporary file's, owner only)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        if mode is not None:
            os.chmod(fd, mode)
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except FileNotFoundError:
            pass
        raise
    dir_fd = os.open(path.parent, os.O_RDONLY)
    try:
        os.fsync(dir_fd)  # make the rename itself durable
    finally:
        os.close(dir_fd)
