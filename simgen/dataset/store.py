"""The writer's view of a dataset store: root attrs, manifest, lock, resume reconciliation.

Layout (Zarr v3, docs/architecture.md "Dataset store")::

    DATASET/zarr.json            root attrs: format_version, simgen_version, spec, content_key/hash,
                                 body {id, hash, source}, garment {name, hash, ...}, material, solver
    DATASET/template/            vertices (V,3) T_r, smoothed (V,3) T_c, faces (F,3), skin_weights (V,24),
                                 garment_template (V,3) (the cloth's rest shape); attrs: smoothing, stats
    DATASET/fit/<shape>/         betas (B,), vertices (V,3) S_c(beta,0), fit_displacement (V,3)
                                 [+ rest_vertices (R,V,3)]; attrs: shape_id, stats
    DATASET/sequences/<id>/      garment_vertices (T,V,3), poses (T,24,3), trans (T,3), betas (T,B)
                                 [+ rest_garment_vertices (R,V,3)], stats/<key> (T,); attrs: motion, fps,
                                 split, shape_id, frames, stats {...}, commit
    DATASET/manifest.json        completed ids with checksums (+ failed ids), rewritten atomically
    DATASET/.lock                pid and host of the running writer (local stores)
    DATASET/.staging/            nodes being written (local stores)

The driver (one process) owns the manifest; nodes may be written by other processes (Ray tasks).
A node is in the dataset when it is committed (see :mod:`simgen.dataset.storage`); the manifest
lists them with checksums. On every run :meth:`DatasetStore.reconcile` makes the two agree: staged
leftovers are removed, committed nodes missing from the manifest (written just before a kill) are
verified against their checksum and adopted, manifest entries whose node is gone are dropped (and
redone).
"""

from __future__ import annotations

import json
import os
import socket
import time

import numpy as np

from simgen.dataset.storage import FORMAT_VERSION, MANIFEST, STAGING, Location, arrays_checksum
from simgen.errors import InputError

__all__ = ["DatasetStore", "node_arrays", "empty_manifest", "read_manifest", "KINDS"]

KINDS = ("template", "fit", "sequences")
_LOCK = ".lock"


def empty_manifest() -> dict:
    return {"format_version": FORMAT_VERSION, "kind": "simgen-dataset-manifest", "updated": None,
            "template": None, "fits": {}, "sequences": {}, "failed": {}}


def read_manifest(loc: Location) -> dict | None:
    """The parsed manifest.json, or None when there is none. InputError when it is corrupt."""
    raw = loc.read_bytes(MANIFEST)
    if raw is None:
        return None
    try:
        doc = json.loads(raw)
    except ValueError as exc:
        raise InputError(f"dataset manifest {loc.url(MANIFEST)} is not valid JSON ({exc})") from None
    if not isinstance(doc, dict) or doc.get("kind") != "simgen-dataset-manifest":
        raise InputError(f"{loc.url(MANIFEST)} is not a simgen dataset manifest")
    base = empty_manifest()
    base.update(doc)
    return base


def node_arrays(loc: Location, rel: str) -> dict[str, np.ndarray]:
    """Every array of the node at ``rel`` (sub-group arrays as 'sub/name'), read in full."""
    import zarr

    out: dict[str, np.ndarray] = {}

    def walk(group, prefix):
        for name, arr in group.arrays():
            out[prefix + name] = arr[...]
        for name, sub in group.groups():
            walk(sub, prefix + name + "/")

    walk(zarr.open_group(loc.url(rel), mode="r"), "")
    return out


class DatasetStore:
    """Writer-side handle of one store (one garment + material). Use :meth:`open_for_writing`."""

    def __init__(self, loc: Location, manifest: dict, attrs: dict) -> None:
        self.loc, self.manifest, self.attrs = loc, manifest, attrs
        self._locked = False

    # ------------------------------------------------------------------ opening
    @classmethod
    def open_for_writing(cls, loc: Location, root_attrs: dict) -> DatasetStore:
        """Create the store, or open an existing one made with the same content key.

        root_attrs must hold 'content_key' and 'content_hash'; they are compared with the stored
        ones (a mismatch raises InputError naming the first differing field), and so are the solver
        settings and material as resolved (``solver.config``, ``material``), which also hold the
        defaults that the key leaves out: a store is never resumed with other physics. Takes the lock.
        """
        import zarr

        existing = loc.node_attrs("")
        manifest = read_manifest(loc) if existing is not None else None
        if existing is None or manifest is None:
            if existing is None and loc.is_local and loc.exists() and any(
                    n not in (STAGING, _LOCK, MANIFEST) for n in loc.listdir("")):
                raise InputError(f"--out {loc.root} exists and is not a simgen dataset store; choose another folder")
            if existing is not None and existing.get("format_version") is None:
                raise InputError(f"--out {loc.root} holds a Zarr group that is not a simgen dataset store")
        if existing is not None and manifest is not None:
            old = existing.get("content_key") or {}
            new = root_attrs["content_key"]
            if existing.get("content_hash") != root_attrs["content_hash"]:
                diff = next((k for k in sorted(set(old) | set(new)) if old.get(k) != new.get(k)), "?")
                raise InputError(f"the store {loc.root} was made with a different spec (field {diff!r}: "
                                 f"{old.get(diff)!r} there, {new.get(diff)!r} now); use another --out")
            if existing.get("format_version") != FORMAT_VERSION:
                raise InputError(f"the store {loc.root} has format version {existing.get('format_version')}, "
                                 f"this simgen writes {FORMAT_VERSION}")
            changed = _resolved_change(existing, root_attrs)
            if changed is not None:
                raise InputError(f"the store {loc.root} was simulated with {changed} (a default that the spec "
                                 f"leaves implicit has changed since); use another --out")
        store = cls(loc, manifest or empty_manifest(), dict(root_attrs))
        fresh = existing is None or manifest is None
        if not fresh:
            store._lock()
        attrs = dict(root_attrs)
        attrs["created"] = ((existing or {}).get("created") if not fresh else None) or time.time()
        attrs["updated"] = time.time()
        from simgen.dataset.storage import StoreWriteError, _jsonable

        try:
            if fresh:
                # Root, the two parent groups, the lock, then the manifest: a create killed before the
                # manifest is redone from scratch (mode "w" clears what it left).
                root = zarr.open_group(loc.url(), mode="w", zarr_format=3, attributes=_jsonable(attrs))
                root.require_group("fit")
                root.require_group("sequences")
                store._lock()
                store.save_manifest()
            else:
                zarr.open_group(loc.url(), mode="r+").attrs.update(_jsonable(attrs))
        except OSError as exc:
            store.release()
            raise StoreWriteError(f"could not create the dataset store {loc.root} ({exc.strerror or exc})") from None
        store.attrs = attrs
        return store

    def _lock(self) -> None:
        if not self.loc.is_local:
            return  # object stores: one driver at a time is the user's responsibility
        raw = self.loc.read_bytes(_LOCK)
        if raw:
            try:
                info = json.loads(raw)
                pid, host = int(info["pid"]), info["host"]
            except (ValueError, KeyError, TypeError):
                pid, host = -1, ""
            if host == socket.gethostname() and pid != os.getpid() and _alive(pid):
                raise InputError(f"another `simgen dataset generate` (pid {pid}) is writing to {self.loc.root}; "
                                 f"wait for it or stop it")
        os.makedirs(self.loc.root, exist_ok=True)
        self.loc.write_bytes(_LOCK, json.dumps({"pid": os.getpid(), "host": socket.gethostname(),
                                                "time": time.time()}).encode())
        self._locked = True

    def release(self) -> None:
        """Drop the lock (the store stays valid without it)."""
        if self._locked:
            self.loc.remove(_LOCK)
            self._locked = False

    # ------------------------------------------------------------------ manifest
    def save_manifest(self) -> None:
        self.manifest["updated"] = time.time()
        self.loc.write_bytes(MANIFEST, json.dumps(self.manifest, indent=1, sort_keys=True).encode())

    def done(self, kind: str, node_id: str | None = None) -> bool:
        if kind == "template":
            return self.manifest["template"] is not None
        return node_id in self.manifest["fits" if kind == "fit" else "sequences"]

    def record(self, outcome: dict) -> None:
        """Enter one job outcome (see :func:`simgen.dataset.execute.run_pool_task`) into the manifest (not saved)."""
        kind, node_id = outcome["kind"], outcome["id"]
        key = f"{kind}:{node_id}"
        if outcome["ok"]:
            entry = {"checksum": outcome["checksum"]}
            if kind == "template":
                self.manifest["template"] = entry
            elif kind == "fit":
                self.manifest["fits"][node_id] = entry
            else:
                entry.update({k: outcome[k] for k in ("frames", "motion", "shape_id", "split")})
                self.manifest["sequences"][node_id] = entry
            self.manifest["failed"].pop(key, None)
        else:
            self.manifest["failed"][key] = {"message": outcome["message"], "attempts": outcome["attempt"]}

    # ------------------------------------------------------------------ reconcile
    def reconcile(self) -> dict:
        """Make manifest and store agree after an interruption (module doc). Returns counts of what
        was done: staging_removed, leftovers_removed, adopted, dropped, corrupt_removed."""
        loc, m = self.loc, self.manifest
        report = dict(staging_removed=0, leftovers_removed=0, adopted=0, dropped=0, corrupt_removed=0)
        if loc.is_local:
            report["staging_removed"] = len(loc.listdir(STAGING))
            loc.remove(STAGING)
        nodes = []
        if loc.node_attrs("template") is not None:
            nodes.append(("template", "template", None))
        for kind, folder in (("fit", "fit"), ("sequences", "sequences")):
            for name in loc.listdir(folder):
                if name == "zarr.json":
                    continue
                nodes.append((kind, f"{folder}/{name}", name))
        present = set()
        for kind, rel, node_id in nodes:
            commit = loc.committed(rel)
            if commit is None:
                loc.remove(rel)
                report["leftovers_removed"] += 1
                continue
            present.add(rel)
            entry = (m["template"] if kind == "template" else m["fits" if kind == "fit" else "sequences"].get(node_id))
            if entry is not None and entry.get("checksum") == commit["checksum"]:
                continue
            # Committed but not (or differently) in the manifest: verify its content and adopt it.
            try:
                ok = arrays_checksum(node_arrays(loc, rel)) == commit["checksum"]
            except Exception:  # noqa: BLE001 - an unreadable node is as good as corrupt
                ok = False
            if not ok:
                loc.remove(rel)
                present.discard(rel)
                report["corrupt_removed"] += 1
                self._forget(kind, node_id)
                continue
            attrs = loc.node_attrs(rel) or {}
            outcome = {"ok": True, "kind": "sequence" if kind == "sequences" else kind, "id": node_id or "template",
                       "checksum": commit["checksum"], "frames": attrs.get("frames"), "motion": attrs.get("motion"),
                       "shape_id": attrs.get("shape_id"), "split": attrs.get("split")}
            self.record(outcome)
            report["adopted"] += 1
        if m["template"] is not None and "template" not in present:
            m["template"] = None
            report["dropped"] += 1
        for kind, folder in (("fits", "fit"), ("sequences", "sequences")):
            for node_id in list(m[kind]):
                if f"{folder}/{node_id}" not in present:
                    del m[kind][node_id]
                    report["dropped"] += 1
        self.save_manifest()
        return report

    def _forget(self, kind: str, node_id: str | None) -> None:
        if kind == "template":
            self.manifest["template"] = None
        else:
            self.manifest["fits" if kind == "fit" else "sequences"].pop(node_id, None)


def _alive(pid: int) -> bool:
    if pid <= 0:
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    # A zombie (killed, not yet reaped by its parent) is not a writer any more.
    try:
        with open(f"/proc/{pid}/stat") as fh:
            return fh.read().split(")")[-1].split()[0] != "Z"
    except OSError:
        return True


def _resolved_change(existing: dict, root_attrs: dict) -> str | None:
    """The first solver setting or material field that resolves differently in ``root_attrs`` than
    in a store's ``existing`` attributes, as "solver setting 'friction.max_normal_load' = A there, B
    now"; None when they agree. Compared as stored (non-finite floats become null); settings the
    store does not hold (added since it was made), the material's citation and stores without these
    attributes (made before they were written, soft-tissue stores) are left out."""
    from simgen.dataset.storage import _jsonable

    def flat(d: dict, prefix: str = "") -> dict:
        out = {}
        for k, v in d.items():
            out.update(flat(v, f"{prefix}{k}.") if isinstance(v, dict) else {f"{prefix}{k}": v})
        return out

    pairs = (("solver setting", (existing.get("solver") or {}).get("config"),
              (root_attrs.get("solver") or {}).get("config")),
             ("material field", existing.get("material"), root_attrs.get("material")))
    for label, old, new in pairs:
        if old is None or new is None:
            continue
        old, new = (flat(json.loads(json.dumps(_jsonable(d)))) for d in (old, new))
        for key in sorted(old):
            if key != "source" and key in new and old[key] != new[key]:
                return f"{label} {key!r} = {old[key]!r} there, {new[key]!r} now"
    return None
