"""Soft-tissue datasets: SoftSMPL's ground truth (thesis ch. 3) simulated by :mod:`simgen.softtissue`.

Every shape of a spec does every motion (and its left-right mirror image, the thesis's
augmentation); each (motion, mirror) is one batched simulation of the shapes not stored yet, and
each shape's result is one committed node. The store has the garment stores' guarantees
(:mod:`simgen.dataset.store`: staged writes, commit records with checksums, a manifest the driver
rewrites, reconciliation after a kill, a lock), so a killed run resumes with the same command.

Layout (Zarr v3)::

    DATASET/zarr.json                 root attrs: format_version, kind "softtissue", spec, content_key/hash,
                                      body {id, hash, source, num_betas}, mesh {nodes, tets, hash}, flesh
    DATASET/sequences/<id>/           displacements (T,V,3) [m] Delta in the unposed frame (x = skin(T +
                                      B_s + B_p + Delta)), poses (T,72) [rad], trans (T,3) [m], betas (B,);
                                      attrs: motion, mirrored, shape_id, split, fps, frames, stats, meta, commit
    DATASET/manifest.json, .lock, .staging/   as in garment stores

Sequence ids are ``<motion>[_mirror]__<shape>``. Read a store for training with
:func:`read_softtissue_store` (``simgen train softtissue --data STORE``), check it with
:func:`check_softtissue_store` (``simgen dataset check STORE``).
"""

from __future__ import annotations

import hashlib
import json
import time
import tomllib
from dataclasses import asdict, dataclass, field, fields, replace
from pathlib import Path

import numpy as np

from simgen.errors import InputError
from simgen.softtissue.params import FleshParams

__all__ = ["SoftTissueSpec", "load_softtissue_spec", "is_softtissue_spec", "is_softtissue_store",
           "generate_softtissue", "read_softtissue_store", "read_store_rows", "check_softtissue_store", "list_softtissue_presets",
           "SoftTissueReport", "sequence_id", "planned_frames"]

PRESETS_DIR = Path(__file__).parent / "presets"
KIND = "softtissue"
MAX_PEAK = 0.10   # [m] largest displacement the check accepts (the validation's peaks are 1-4 cm)


@dataclass(frozen=True)
class SoftTissueSpec:
    """What a soft-tissue store holds (a TOML file with ``kind = "softtissue"``; see the presets).

    name: the store's name; body: "open" or an SMPL file; mesh: a flesh mesh file (None: the body's
    bundled one); shapes: ((id, betas), ...) with betas [-] as long as the body's or shorter
    (zeros follow); motions: library clip names; test_motions: held out (split "test"; default: the
    library's test clips); mirror: also each clip's mirror image; clip_start [s], max_seconds [s]
    (None: to the end): the window of each clip simulated; batch_size: (clip, shape) sequences per
    batched simulation (0: the number of shapes); device: "auto", "cpu", "cuda:N"; flesh: the simulation's
    :class:`simgen.softtissue.FleshParams`; output: default store folder; description: one line.
    """

    name: str
    shapes: tuple
    motions: tuple
    body: str = "open"
    mesh: str | None = None
    test_motions: tuple | None = None
    mirror: bool = True
    clip_start: float = 0.0
    max_seconds: float | None = None
    batch_size: int = 0
    device: str = "auto"
    flesh: FleshParams = field(default_factory=FleshParams)
    output: str | None = None
    description: str = ""
    source: str = field(default="", compare=False)

    def resolved_device(self) -> str:
        if self.device != "auto":
            return self.device
        import warp as wp

        return "cuda:0" if wp.get_cuda_device_count() > 0 else "cpu"

    def split(self, motion: str) -> str:
        if self.test_motions is not None:
            return "test" if motion in self.test_motions else "train"
        from simgen.motion.library import library_split

        return "test" if motion in library_split()["test"] else "train"

    def plan(self) -> list[tuple[str, bool]]:
        """(motion, mirrored) of every simulation, in order."""
        return [(m, mirrored) for m in self.motions for mirrored in ((False, True) if self.mirror else (False,))]

    def content_key(self) -> dict:
        """What the stored data depends on (not where it goes or on what device)."""
        d = self.to_dict()
        for k in ("output", "device", "batch_size", "source", "description"):
            d.pop(k, None)
        return d

    def to_dict(self) -> dict:
        d = {f.name: getattr(self, f.name) for f in fields(self) if f.name != "flesh"}
        d["shapes"] = [{"id": i, "betas": list(b)} for i, b in self.shapes]
        d["motions"] = list(self.motions)
        d["test_motions"] = None if self.test_motions is None else list(self.test_motions)
        d["flesh"] = asdict(self.flesh)
        return json.loads(json.dumps(d))

    def output_path(self, out: str | None = None) -> str:
        return out if out is not None else (self.output or f"datasets/{self.name}")


_FIELDS = {"kind", "name", "description", "body", "mesh", "shapes", "motions", "test_motions", "mirror", "clip_start",
           "max_seconds", "batch_size", "device", "flesh", "output"}


def list_softtissue_presets() -> list[str]:
    """Names of the bundled soft-tissue presets."""
    return sorted(p.stem for p in PRESETS_DIR.glob("*.toml") if is_softtissue_spec(p))


def is_softtissue_spec(spec) -> bool:
    """Whether ``spec`` (a spec object, a preset name or a TOML path) is a soft-tissue spec."""
    if isinstance(spec, SoftTissueSpec):
        return True
    if not isinstance(spec, (str, Path)):
        return False
    path = _spec_path(spec)
    if path is None or not path.is_file():
        return False
    try:
        return tomllib.loads(path.read_text(encoding="utf-8")).get("kind") == KIND
    except (UnicodeDecodeError, tomllib.TOMLDecodeError):
        return False


def _spec_path(spec) -> Path | None:
    text = str(spec)
    path = Path(text).expanduser()
    if path.suffix != ".toml" and "/" not in text and not path.exists():
        path = PRESETS_DIR / f"{text}.toml"
    return path


def load_softtissue_spec(spec) -> SoftTissueSpec:
    """A soft-tissue spec from a preset name, a TOML path or a dict. InputError names the bad field."""
    if isinstance(spec, SoftTissueSpec):
        return spec
    source = "<dict>"
    if isinstance(spec, dict):
        doc = spec
    else:
        path = _spec_path(spec)
        if path is None or not path.is_file():
            raise InputError(f"soft-tissue spec {spec} does not exist")
        try:
            doc = tomllib.loads(path.read_text(encoding="utf-8"))
        except (UnicodeDecodeError, tomllib.TOMLDecodeError) as exc:
            raise InputError(f"soft-tissue spec {path} is not valid TOML ({exc})") from None
        source = str(path)
    return _parse(doc, source)


def _parse(doc: dict, source: str) -> SoftTissueSpec:
    where = f"soft-tissue spec {source}"
    unknown = sorted(set(doc) - _FIELDS)
    if unknown:
        raise InputError(f"{where}: unknown field {unknown[0]!r} (known: {', '.join(sorted(_FIELDS))})")
    if doc.get("kind", KIND) != KIND:
        raise InputError(f"{where}: kind must be {KIND!r}, got {doc.get('kind')!r}")

    def names(key, required):
        v = doc.get(key)
        if v is None and not required:
            return None
        if not isinstance(v, list) or not v or not all(isinstance(n, str) and n for n in v):
            raise InputError(f"{where}: {key} must be a non-empty list of names, got {v!r}")
        if len(set(v)) != len(v):
            raise InputError(f"{where}: {key} lists a name twice")
        return tuple(v)

    shapes = []
    for k, s in enumerate(doc.get("shapes") or []):
        sid, betas = (s.get("id"), s.get("betas", [])) if isinstance(s, dict) else (None, None)
        if not isinstance(sid, str) or not sid or "__" in sid or not isinstance(betas, list) or \
                not all(isinstance(b, (int, float)) and np.isfinite(b) for b in betas):
            raise InputError(f"{where}: shapes[{k}] must be {{id = NAME (no '__'), betas = [numbers]}}, got {s!r}")
        shapes.append((sid, tuple(float(b) for b in betas)))
    if not shapes or len({i for i, _ in shapes}) != len(shapes):
        raise InputError(f"{where}: shapes must list at least one shape, each id once")
    motions = names("motions", True)
    bad = [m for m in motions if "__" in m or m.endswith("_mirror")]
    if bad:
        raise InputError(f"{where}: motion name {bad[0]!r} may not contain '__' or end in '_mirror'")
    test_motions = names("test_motions", False)
    if test_motions is not None and not set(test_motions) <= set(motions):
        raise InputError(f"{where}: test_motions names {sorted(set(test_motions) - set(motions))[0]!r}, which is not "
                         f"in motions")
    flesh = doc.get("flesh") or {}
    if not isinstance(flesh, dict):
        raise InputError(f"{where}: [flesh] must be a table of FleshParams fields")
    try:
        params = FleshParams(**flesh)
    except (TypeError, InputError) as exc:
        raise InputError(f"{where}: [flesh]: {exc}") from None
    num = {"clip_start": (0.0, float), "max_seconds": (0.0, float), "batch_size": (0, int)}
    values = {}
    for key, (low, kind) in num.items():
        v = doc.get(key)
        if v is None:
            continue
        if isinstance(v, bool) or not isinstance(v, (int, float)) or (kind is int and not isinstance(v, int)) \
                or not v >= low or (key == "max_seconds" and not v > 0):
            raise InputError(f"{where}: {key} must be a number >= {low}{' (> 0)' if key == 'max_seconds' else ''}, "
                             f"got {v!r}")
        values[key] = kind(v)
    for key in ("body", "mesh", "device", "output", "name"):
        if key in doc and not (isinstance(doc[key], str) and doc[key]):
            raise InputError(f"{where}: {key} must be a non-empty string, got {doc[key]!r}")
    if not isinstance(doc.get("description", ""), str):
        raise InputError(f"{where}: description must be a string, got {doc['description']!r}")
    if "mirror" in doc and not isinstance(doc["mirror"], bool):
        raise InputError(f"{where}: mirror must be true or false, got {doc['mirror']!r}")
    name = doc.get("name") or (Path(source).stem if source != "<dict>" else None)
    if not name:
        raise InputError(f"{where}: name is missing")
    base = Path(source).resolve().parent if source != "<dict>" else None
    return SoftTissueSpec(name=name, shapes=tuple(shapes), motions=motions,
                          body=_beside(doc.get("body", "open"), base), mesh=_beside(doc.get("mesh"), base),
                          test_motions=test_motions,
                          mirror=doc.get("mirror", True), device=doc.get("device", "auto"), flesh=params,
                          output=doc.get("output"), description=doc.get("description", ""), source=source,
                          **values)


def _beside(value: str | None, base: Path | None) -> str | None:
    """A file named in a spec, relative to the spec's folder (a body name such as "open" as it is)."""
    if value is None or base is None or Path(value).is_absolute():
        return value
    if "/" in value or Path(value).suffix.lower() in (".pkl", ".npz"):
        return str(base / value)
    return value


# ------------------------------------------------------------------------------------------ writing
@dataclass
class SoftTissueReport:
    """What one run did: path, planned/written/pending sequences, frames simulated, wall [s],
    the simulation's share of it [s], why it stopped early (None: it did not), and the sequences
    that failed ({id: message}: not written; a rerun simulates them again)."""

    path: str
    planned: int
    done_before: int
    written: int = 0
    failed: dict = field(default_factory=dict)
    pending: int = 0
    frames: int = 0
    wall: float = 0.0
    simulate_wall: float = 0.0
    stopped: str | None = None
    reconcile: dict = field(default_factory=dict)

    def to_dict(self) -> dict:
        return asdict(self)


def sequence_id(motion: str, mirrored: bool, shape_id: str) -> str:
    return f"{motion}{'_mirror' if mirrored else ''}__{shape_id}"


def _mesh_hash(mesh) -> str:
    h = hashlib.sha256()
    for a in (mesh.nodes, mesh.tets):
        h.update(np.ascontiguousarray(a).tobytes())
    return h.hexdigest()


def _root_attrs(spec: SoftTissueSpec, body, mesh) -> dict:
    from simgen import __version__
    from simgen.dataset.storage import FORMAT_VERSION

    key = spec.content_key()
    key["body_hash"] = body.hash
    key["mesh_hash"] = _mesh_hash(mesh)
    return {"format_version": FORMAT_VERSION, "simgen_version": __version__, "kind": KIND, "spec": spec.to_dict(),
            "content_key": key, "content_hash": hashlib.sha256(json.dumps(key, sort_keys=True).encode()).hexdigest(),
            "body": {"id": body.model_id, "hash": body.hash, "source": spec.body, "num_betas": body.num_betas,
                     "vertices": body.num_vertices},
            "mesh": {"nodes": int(mesh.num_nodes), "tets": int(mesh.num_tets), "hash": key["mesh_hash"]},
            "flesh": asdict(spec.flesh)}


def _clip(spec: SoftTissueSpec, motion: str, mirrored: bool):
    from simgen.motion.library import load_motion
    from simgen.motion.ops import mirror, trim

    clip = load_motion(motion)
    end = clip.duration if spec.max_seconds is None else min(clip.duration, spec.clip_start + spec.max_seconds)
    if not (end - spec.clip_start) * spec.flesh.rate >= 2.0:
        raise InputError(f"soft-tissue spec {spec.source or spec.name}: motion {motion!r} ({clip.duration:.2f} s) leaves "
                         f"no window of at least 3 steps from clip_start {spec.clip_start:g} s")
    clip = trim(clip, spec.clip_start, end)
    return mirror(clip) if mirrored else clip


def planned_frames(spec: SoftTissueSpec) -> int:
    """Stored frames of a spec's whole plan: every shape of every (motion, mirror), at the flesh's fps."""
    per_motion = [int(np.floor(_clip(spec, m, False).duration * spec.flesh.fps + 1e-9)) + 1 for m in spec.motions]
    return sum(per_motion) * len(spec.shapes) * (2 if spec.mirror else 1)


def _betas(spec: SoftTissueSpec, body, ids: list[str]) -> np.ndarray:
    """(N, B) betas of the shapes ``ids``, zero-padded to the body's (InputError names the shape)."""
    table = dict(spec.shapes)
    out = []
    for sid in ids:
        try:
            out.append(body.check_betas(table[sid])[0])
        except InputError as exc:
            raise InputError(f"soft-tissue spec {spec.source or spec.name}: shape {sid!r}: {exc}") from None
    return np.stack(out) if out else np.zeros((0, body.num_betas))


def _node(spec: SoftTissueSpec, res, motion: str, mirrored: bool, shape_id: str) -> tuple[dict, dict]:
    from simgen.softtissue.simulate import mean_speed

    d = np.asarray(res.displacements, dtype=np.float32)
    mag = np.linalg.norm(d, axis=-1)                                      # (T, V) [m]
    arrays = {"displacements": d, "poses": np.asarray(res.poses, dtype=np.float32),
              "trans": np.asarray(res.trans, dtype=np.float32), "betas": np.asarray(res.betas, dtype=np.float32)}
    stats = {"peak_m": float(mag.max(initial=0.0)), "mean_m": float(mag.mean()) if mag.size else 0.0,
             "mean_speed_mps": mean_speed(d, res.fps), "min_det": float(res.meta["min_det"]),
             "cg_iterations_max": int(res.meta["cg_iterations_max"]), "cg_capped": int(res.meta["cg_capped"])}
    attrs = {"motion": motion, "mirrored": bool(mirrored), "shape_id": shape_id, "split": spec.split(motion),
             "fps": float(res.fps), "frames": int(len(d)), "stats": stats,
             "meta": {k: v for k, v in res.meta.items() if k not in ("params",)}}
    return arrays, attrs


def generate_softtissue(spec, out: str | None = None, *, max_sequences: int | None = None,
                        time_budget: float | None = None, progress=None, log=None) -> SoftTissueReport:
    """Generate (or resume) a soft-tissue store. progress(done, total) in sequences; log(str).

    time_budget [s]: start no simulation that would not end in time (estimated from the ones run);
    max_sequences: at most this many new sequences. Raises InputError for bad input,
    StoreWriteError when the store cannot be written (it stays consistent and resumable).
    """
    from simgen import body as body_pkg
    from simgen._warp_log import quiet_warp
    from simgen.dataset.storage import Location
    from simgen.dataset.store import DatasetStore
    from simgen.softtissue.mesh import flesh_mesh

    quiet_warp()
    spec = load_softtissue_spec(spec)
    say = log or (lambda msg: None)
    body = body_pkg.load(spec.body)
    mesh = flesh_mesh(body, spec.mesh)
    for motion in spec.motions:
        _clip(spec, motion, False)   # every clip loads and is long enough, before anything is written
    _betas(spec, body, [sid for sid, _ in spec.shapes])
    t0 = time.perf_counter()
    loc = Location(spec.output_path(out))
    store = DatasetStore.open_for_writing(loc, _root_attrs(spec, body, mesh))
    try:
        rec = store.reconcile()
        if any(rec.values()):
            say(f"{loc.root}: resumed ({', '.join(f'{k} {v}' for k, v in rec.items() if v)})")
        planned = [(m, r, sid) for m, r in spec.plan() for sid, _ in spec.shapes]
        report = SoftTissueReport(path=loc.root, planned=len(planned), done_before=len(store.manifest["sequences"]),
                                  reconcile=rec)
        _run(spec, store, body, mesh, report, max_sequences, time_budget, t0, progress)
        report.pending = len(planned) - len(store.manifest["sequences"])
        report.wall = time.perf_counter() - t0
        return report
    finally:
        store.save_manifest()
        store.release()


def _run(spec, store, body, mesh, report, max_sequences, time_budget, t0, progress) -> None:
    """Simulate the sequences not stored yet, ``spec.batch_size`` (clip, shape) jobs per batched
    simulation, each batch's writes in a thread behind the next batch's simulation."""
    from concurrent.futures import ThreadPoolExecutor

    from simgen.softtissue.simulate import simulate_softtissue_jobs

    device = spec.resolved_device()
    todo = [(m, r, sid) for m, r in spec.plan() for sid, _ in spec.shapes
            if not store.done("sequence", sequence_id(m, r, sid))]
    if max_sequences is not None and len(todo) > max_sequences:
        todo = todo[:max(max_sequences, 0)]
        report.stopped = f"--max-sequences {max_sequences} reached"
    size = spec.batch_size or len(spec.shapes)
    groups = [todo[i:i + size] for i in range(0, len(todo), size)]
    clips = {}

    def clip(m, r):
        if (m, r) not in clips:
            c = _clip(spec, m, r)
            clips[(m, r)] = replace(c, name=m + ("_mirror" if r else ""))
        return clips[(m, r)]

    # A batch costs about the same however many jobs it holds (its steps are launch-bound): the
    # budget test takes the last batch's wall per stored frame of its longest clip.
    done, per_frame_s, pending = 0, None, None
    with ThreadPoolExecutor(1) as writer:
        try:
            for group in groups:
                longest = max(int(np.floor(clip(m, r).duration * spec.flesh.fps + 1e-9)) + 1 for m, r, _ in group)
                if time_budget is not None and per_frame_s is not None and \
                        time.perf_counter() - t0 + per_frame_s * longest > time_budget:
                    report.stopped = f"time budget of {time_budget:g} s reached"
                    break
                t = time.perf_counter()
                jobs = [(clip(m, r), _betas(spec, body, [sid])[0], sid) for m, r, sid in group]
                results = simulate_softtissue_jobs(body, jobs, spec.flesh, mesh=mesh, device=device)
                wall = time.perf_counter() - t
                report.simulate_wall += wall
                per_frame_s = wall / longest
                if pending is not None:
                    done += _record(store, report, pending.result())
                pending = writer.submit(_write_group, spec, store, group, results)
                if progress is not None:
                    progress(done, len(todo))
        finally:   # what was written is entered in the manifest, also when a simulation raised
            if pending is not None:
                done += _record(store, report, pending.result())
                if progress is not None:
                    progress(done, len(todo))


def _write_group(spec, store, group, results) -> list:
    """Write one batch's sequences (in the writer thread); what :func:`_record` enters in the manifest."""
    out = []
    for (motion, mirrored, sid), res in zip(group, results):
        node = sequence_id(motion, mirrored, sid)
        if not (np.all(np.isfinite(res.displacements)) and np.isfinite(res.meta["min_det"])):
            out.append((node, None, {"message": "the simulation produced non-finite displacements (not written; a "
                                                "rerun simulates it again)"}))
            continue
        arrays, attrs = _node(spec, res, motion, mirrored, sid)
        commit = store.loc.write_node(f"sequences/{node}", arrays, attrs)
        out.append((node, commit, attrs))
    return out


def _record(store, report, written: list) -> int:
    """Enter a written batch in the manifest (main thread); the number of sequences it held."""
    for node, commit, attrs in written:
        if commit is None:
            store.record({"ok": False, "kind": "sequence", "id": node, "attempt": 1, "message": attrs["message"]})
            report.failed[node] = attrs["message"]
            continue
        store.record({"ok": True, "kind": "sequence", "id": node, "checksum": commit["checksum"],
                      "frames": attrs["frames"], "motion": attrs["motion"], "shape_id": attrs["shape_id"],
                      "split": attrs["split"]})
        report.written += 1
        report.frames += attrs["frames"]
    store.save_manifest()
    return len(written)


# ------------------------------------------------------------------------------------------ reading
def is_softtissue_store(path) -> bool:
    """Whether ``path`` (a folder or URL) holds a soft-tissue store."""
    from simgen.dataset.storage import Location

    try:
        attrs = Location(str(path)).node_attrs("")
    except (OSError, ValueError):
        return False
    return bool(attrs) and attrs.get("kind") == KIND


def _open(path):
    from simgen.dataset.storage import Location
    from simgen.dataset.store import read_manifest

    loc = Location(str(path))
    attrs = loc.node_attrs("")
    if not attrs or attrs.get("kind") != KIND:
        raise InputError(f"{path} is not a simgen soft-tissue store")
    manifest = read_manifest(loc)
    if manifest is None:
        raise InputError(f"{path}: the soft-tissue store has no manifest")
    return loc, attrs, manifest


def store_body(path, body=None):
    """The body model of a store: ``body`` (a BodyModel or source) checked against the store's hash,
    or the one the store was made with."""
    from simgen import body as body_pkg

    _, attrs, _ = _open(path)
    if body is None:
        body = attrs["body"]["source"]
    body = body if not isinstance(body, (str, Path)) else body_pkg.load(str(body))
    if body.hash != attrs["body"]["hash"]:
        raise InputError(f"{path} was made with body {attrs['body']['id']!r} (hash {attrs['body']['hash'][:12]}); "
                         f"the body given has hash {body.hash[:12]}")
    return body


def read_softtissue_store(path, *, body=None, max_frames: int | None = None, sequences=None):
    """The committed sequences of a store as :class:`simgen.learn.softtissue.SoftTissueData` (the
    shapes are its subjects; a mirrored clip keeps its motion's name, so a held-out motion holds
    out its mirror too; each sequence's ``meta['split']`` is the store's). body: the body model
    (default: the store's, checked by hash, :func:`store_body`); max_frames: at most this many
    frames per sequence; sequences: only these ids (InputError for one the store lacks)."""
    import zarr

    from simgen.learn.softtissue.data import SoftTissueData, SoftTissueSequence

    loc, attrs, manifest = _open(path)
    body = store_body(path, body)
    chosen = sorted(manifest["sequences"]) if sequences is None else list(sequences)
    missing = [n for n in chosen if n not in manifest["sequences"]]
    if missing:
        raise InputError(f"{path} has no sequence {missing[0]!r} (`simgen dataset info {path}` lists them)")
    seqs = []
    for node in chosen:
        g = zarr.open_group(loc.url(f"sequences/{node}"), mode="r")
        a = dict(g.attrs)
        n = a["frames"] if max_frames is None else min(a["frames"], max_frames)
        seqs.append(SoftTissueSequence(
            name=node, subject=a["shape_id"], motion=a["motion"], betas=g["betas"][...], poses=g["poses"][:n],
            trans=g["trans"][:n], fps=a["fps"], displacements=g["displacements"][:n],
            meta={"store": str(path), "mirrored": a["mirrored"], "split": a["split"], **a["meta"]}))
    if not seqs:
        raise InputError(f"{path}: the soft-tissue store has no sequences yet")
    return SoftTissueData(sequences=seqs, body={"id": body.name, "hash": body.hash}, faces=body.faces,
                          template=body.v_template, source=str(path))


def read_store_rows(path) -> tuple[dict, list[dict]]:
    """(head, rows) for ``simgen dataset info``: the store's body, mesh, counts, and per sequence its
    id, motion, mirrored, shape, split, frames and stats (from the attrs; nothing read in full)."""
    loc, attrs, manifest = _open(path)
    rows = []
    for node in sorted(manifest["sequences"]):
        a = loc.node_attrs(f"sequences/{node}") or {}
        rows.append({"id": node, "motion": a.get("motion"), "mirrored": a.get("mirrored"), "shape": a.get("shape_id"),
                     "split": a.get("split"), "frames": a.get("frames"), **(a.get("stats") or {})})
    head = {"path": str(path), "kind": KIND, "body": attrs["body"], "mesh": attrs["mesh"],
            "fps": attrs["flesh"]["fps"], "shapes": [s["id"] for s in attrs["spec"]["shapes"]],
            "sequences": len(rows), "test": sum(r["split"] == "test" for r in rows),
            "frames": sum(r["frames"] or 0 for r in rows), "failed": sorted(manifest.get("failed", {})),
            "simgen_version": attrs.get("simgen_version")}
    return head, rows


def check_softtissue_store(path, *, max_peak: float = MAX_PEAK, require_complete: bool = False,
                           progress=None) -> dict:
    """Check a store: manifest and nodes agree (committed, checksums recomputed), arrays finite and of
    the body's size, frame counts, peaks at most ``max_peak`` [m], no inverted tetrahedron (the
    smallest det(I + grad u) the writer measured, > 0), no failed sequence; with
    ``require_complete`` every planned sequence present. Returns a report {passed, problems [str],
    sequences, frames, max_peak_m, min_det, mean_speed_mps, failed}."""
    import zarr

    from simgen.dataset.storage import arrays_checksum
    from simgen.dataset.store import node_arrays

    loc, attrs, manifest = _open(path)
    problems = [f"{key}: failed ({entry.get('message')})" for key, entry in sorted(manifest["failed"].items())]
    listed = manifest["sequences"]
    on_disk = {n for n in loc.listdir("sequences") if n != "zarr.json"}
    for node in sorted(on_disk - set(listed)):
        problems.append(f"sequences/{node}: in the store but not in the manifest")
    if require_complete:
        spec = _parse({k: v for k, v in attrs["spec"].items() if k != "source" and v is not None}, str(path))
        missing = [n for m, r in spec.plan() for sid, _ in spec.shapes
                   if (n := sequence_id(m, r, sid)) not in listed]
        if missing:
            problems.append(f"{len(missing)} planned sequences missing (first: {missing[0]})")
    V = attrs["body"]["vertices"]
    frames, peak, min_det, speeds = 0, 0.0, np.inf, []
    for k, (node, entry) in enumerate(sorted(listed.items())):
        if progress is not None:
            progress(k + 1, len(listed))
        rel = f"sequences/{node}"
        if loc.committed(rel) is None:
            problems.append(f"{rel}: listed in the manifest but not committed")
            continue
        arrays = node_arrays(loc, rel)
        if arrays_checksum(arrays) != entry["checksum"]:
            problems.append(f"{rel}: checksum differs from the manifest's (corrupt)")
            continue
        d, a = arrays["displacements"], dict(zarr.open_group(loc.url(rel), mode="r").attrs)
        if d.shape[1:] != (V, 3) or len(d) != a["frames"] or len(arrays["poses"]) != len(d):
            problems.append(f"{rel}: displacements {d.shape} and poses {arrays['poses'].shape} disagree with "
                            f"{a['frames']} frames of the body's {V} vertices")
            continue
        if not all(np.all(np.isfinite(x)) for x in arrays.values()):
            problems.append(f"{rel}: non-finite values")
            continue
        p = float(np.linalg.norm(d, axis=-1).max(initial=0.0))
        if p > max_peak:
            problems.append(f"{rel}: a vertex moves {100 * p:.1f} cm from its skinned place (limit {100 * max_peak:g} cm)")
        if not a["stats"]["min_det"] > 0:
            problems.append(f"{rel}: a tetrahedron inverted (min det {a['stats']['min_det']:.3g})")
        frames += len(d)
        peak = max(peak, p)
        min_det = min(min_det, a["stats"]["min_det"])
        speeds.append(a["stats"]["mean_speed_mps"])
    return {"path": str(path), "passed": not problems, "problems": problems, "sequences": len(listed),
            "frames": frames, "max_peak_m": peak, "min_det": None if not np.isfinite(min_det) else float(min_det),
            "mean_speed_mps": float(np.mean(speeds)) if speeds else None, "failed": sorted(manifest["failed"])}
