"""Atomic file writes: write beside the target under a temporary name, then rename into place, so
a crash or a failed check never leaves a half-written file under the real name."""

from __future__ import annotations

import os
import tempfile
import uuid
from pathlib import Path

__all__ = ["atomic_write_bytes", "temp_path_beside"]


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def temp_path_beside(path: str | os.PathLike) -> Path:
    """A fresh hidden name in the target's folder (so the final rename is atomic) that keeps the
    target's suffix (libraries that pick a format from it, such as Sdf and ffmpeg, still work)."""
    path = Path(path)
    return path.parent / f".{path.stem}.{os.getpid()}.{uuid.uuid4().hex[:12]}.tmp{path.suffix}"


def atomic_write_bytes(path: str | os.PathLike, data: bytes) -> Path:
    """Write bytes to `path` atomically, with the permissions a plain open() would give."""
    path = Path(path)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as fh:
            fh.write(data)
        os.chmod(tmp, 0o666 & ~_umask())  # mkstemp creates 0600; library files are for everyone
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path
