"""Where a dataset store lives (a local folder or an fsspec URL) and how nodes are committed.

A *node* is one Zarr group written as a unit: ``template``, ``fit/<shape>`` or ``sequences/<id>``.
A node is complete exactly when its group attrs hold ``commit`` ({checksum, time}); the commit is
the last thing written, and readers ignore nodes without it.

- Local folders: a node is written under ``.staging/<kind>-<id>-<random>/`` (a folder Zarr never
  lists: no zarr.json above it) and renamed into place once committed. ``rename`` of a folder is
  atomic on POSIX, so a killed writer leaves either nothing under the final name or a whole node;
  leftovers in ``.staging/`` are removed on the next run.
- Object stores (fsspec URLs: s3://, gs://, memory://, ...): there is no rename. The node is written
  under its final name and the commit marker (the group's zarr.json with ``commit`` in its attrs,
  one PUT) goes last; a node without the marker is a leftover and is deleted on the next run.

Either way, the first writer of a node wins: a second attempt (a retried Ray task) that finds the
node committed keeps the existing one. Checksums are SHA-256 over every array's name, dtype, shape
and little-endian bytes (sorted by name), so a reader can prove a node holds what was committed.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import time
import uuid
from pathlib import Path

import numpy as np

from simgen.errors import InputError

__all__ = ["Location", "StoreWriteError", "array_checksum", "arrays_checksum", "FORMAT_VERSION", "MANIFEST"]

FORMAT_VERSION = 1
MANIFEST = "manifest.json"
STAGING = ".staging"


class StoreWriteError(InputError):
    """Writing to the store failed (disk full, permissions, network): one sentence, the store stays consistent."""


def array_checksum(h, name: str, a: np.ndarray) -> None:
    """Feed one array into a hashlib object: name, dtype, shape, then its little-endian bytes."""
    a = np.ascontiguousarray(a)
    dt = a.dtype.newbyteorder("<") if a.dtype.byteorder == ">" else a.dtype
    h.update(f"{name}|{dt.str}|{a.shape}|".encode())
    h.update(a.astype(dt, copy=False).tobytes())


def arrays_checksum(arrays: dict[str, np.ndarray]) -> str:
    """SHA-256 (hex) of named arrays (names may contain '/' for sub-groups), order-independent."""
    h = hashlib.sha256()
    for name in sorted(arrays):
        array_checksum(h, name, np.asarray(arrays[name]))
    return h.hexdigest()


def _debug_delay() -> float:
    # Crash tests set this to widen the window in which a node is half-written: seconds slept once,
    # after half of a node's arrays are written.
    try:
        return float(os.environ.get("SIMGEN_DATASET_WRITE_DELAY", "0") or 0)
    except ValueError:
        return 0.0


class Location:
    """A dataset root: local path or fsspec URL. Relative names use '/' separators."""

    def __init__(self, root: str | os.PathLike) -> None:
        text = str(root)
        self.is_local = "://" not in text or text.startswith("file://")
        if self.is_local:
            self.root = str(Path(text.removeprefix("file://")).expanduser().resolve())
            self.fs = None
        else:
            import fsspec

            self.fs, self.fs_root = fsspec.core.url_to_fs(text)
            self.root = text.rstrip("/")

    def __repr__(self) -> str:
        return f"Location({self.root!r})"

    def url(self, rel: str = "") -> str:
        """The path or URL of a name inside the store (what zarr.open_group takes)."""
        if not rel:
            return self.root
        if self.is_local:
            return str(Path(self.root) / rel)
        return f"{self.root}/{rel}"

    def _fs_path(self, rel: str) -> str:
        return f"{self.fs_root.rstrip('/')}/{rel}" if rel else self.fs_root

    # ------------------------------------------------------------------ plain files
    def exists(self, rel: str = "") -> bool:
        if self.is_local:
            return (Path(self.root) / rel).exists()
        return self.fs.exists(self._fs_path(rel))

    def read_bytes(self, rel: str) -> bytes | None:
        """Bytes of a file, or None when it does not exist."""
        try:
            if self.is_local:
                return (Path(self.root) / rel).read_bytes()
            with self.fs.open(self._fs_path(rel), "rb") as fh:
                return fh.read()
        except FileNotFoundError:
            return None

    def write_bytes(self, rel: str, data: bytes) -> None:
        """Write a file atomically (local: temporary name + rename; object store: one PUT)."""
        try:
            if self.is_local:
                from simgen._fileio import atomic_write_bytes

                path = Path(self.root) / rel
                path.parent.mkdir(parents=True, exist_ok=True)
                atomic_write_bytes(path, data)
            else:
                self.fs.pipe_file(self._fs_path(rel), data)
        except OSError as exc:
            raise StoreWriteError(f"could not write {self.url(rel)} ({exc.strerror or exc})") from None

    def listdir(self, rel: str) -> list[str]:
        """Names directly under a folder (empty when it does not exist)."""
        if self.is_local:
            p = Path(self.root) / rel
            return sorted(c.name for c in p.iterdir()) if p.is_dir() else []
        path = self._fs_path(rel)
        if not self.fs.exists(path):
            return []
        return sorted(Path(e.rstrip("/")).name for e in self.fs.ls(path, detail=False))

    def remove(self, rel: str) -> None:
        """Delete a file or folder tree (missing is fine)."""
        if self.is_local:
            p = Path(self.root) / rel
            if p.is_dir():
                shutil.rmtree(p, ignore_errors=True)
            else:
                p.unlink(missing_ok=True)
        else:
            path = self._fs_path(rel)
            if self.fs.exists(path):
                self.fs.rm(path, recursive=True)

    # ------------------------------------------------------------------ nodes
    def node_attrs(self, rel: str) -> dict | None:
        """The attrs of the Zarr group at ``rel`` (None when there is no group there)."""
        raw = self.read_bytes(f"{rel}/zarr.json" if rel else "zarr.json")
        if raw is None:
            return None
        try:
            return json.loads(raw).get("attributes", {}) or {}
        except ValueError:
            return None

    def committed(self, rel: str) -> dict | None:
        """The commit record of a node ({checksum, time}), or None when absent or incomplete."""
        attrs = self.node_attrs(rel)
        if not attrs:
            return None
        c = attrs.get("commit")
        return c if isinstance(c, dict) and "checksum" in c else None

    def write_node(self, rel: str, arrays: dict[str, np.ndarray], attrs: dict, *,
                   chunks: dict[str, tuple] | None = None) -> dict:
        """Write a node (a Zarr group with arrays and attrs) and commit it; returns the commit record.

        arrays: name -> array ('stats/x' creates the sub-group 'stats'); chunks: name -> chunk shape
        (default: one chunk). If the node is already committed (an earlier attempt), nothing is
        written and the existing commit is returned. Raises :class:`StoreWriteError` on I/O failure,
        leaving no committed half node.
        """
        existing = self.committed(rel)
        if existing is not None:
            return existing
        checksum = arrays_checksum(arrays)
        commit = {"checksum": checksum, "time": time.time()}
        if self.is_local:
            kind_id = rel.replace("/", "-")
            stage = f"{STAGING}/{kind_id}-{uuid.uuid4().hex[:12]}"
            target = stage
        else:
            if self.exists(rel):
                self.remove(rel)  # an uncommitted leftover of an attempt that died
            target = rel
        try:
            self._write_group(target, arrays, attrs, chunks or {}, commit)
            if self.is_local:
                dest = Path(self.root) / rel
                dest.parent.mkdir(parents=True, exist_ok=True)
                try:
                    os.rename(Path(self.root) / stage, dest)
                except OSError:
                    if self.committed(rel) is None:
                        raise
                    # Another attempt committed the node first: keep that one.
                    self.remove(stage)
                    return self.committed(rel)
        except BaseException as exc:
            if self.is_local:
                self.remove(stage)
            if isinstance(exc, (OSError, ValueError, RuntimeError)) and not isinstance(exc, InputError):
                raise StoreWriteError(f"could not write {rel} to the dataset store {self.root} "
                                      f"({type(exc).__name__}: {exc}); the store is consistent, rerun the same "
                                      f"command to resume") from exc
            raise
        return commit

    def _write_group(self, target: str, arrays: dict, attrs: dict, chunks: dict, commit: dict) -> None:
        import zarr

        delay = _debug_delay()
        group = zarr.open_group(self.url(target), mode="w", zarr_format=3, attributes=_jsonable(attrs))
        subgroups: dict[str, object] = {}
        names = sorted(arrays)
        for i, name in enumerate(names):
            a = np.ascontiguousarray(arrays[name])
            parent, _, leaf = name.rpartition("/")
            g = group
            if parent:
                if parent not in subgroups:
                    subgroups[parent] = group.require_group(parent)
                g = subgroups[parent]
            fill = np.nan if a.dtype.kind == "f" else 0
            chunk = chunks.get(name) or a.shape
            chunk = tuple(max(1, min(int(c), int(s) if s else 1)) for c, s in zip(chunk, a.shape)) or None
            z = g.create_array(leaf, shape=a.shape, dtype=a.dtype, chunks=chunk, fill_value=fill)
            if a.size:
                z[...] = a
            if delay and i == len(names) // 2:
                time.sleep(delay)
        # The commit marker: rewriting the group's zarr.json with 'commit' is the node's last write.
        group.attrs.update({"commit": commit})


def _jsonable(value):
    """Plain JSON types (numpy scalars and arrays converted) for Zarr attrs."""
    if isinstance(value, dict):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    if isinstance(value, np.ndarray):
        return _jsonable(value.tolist())
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, float) and not np.isfinite(value):
        return None
    return value
