"""Garment sequences to evaluate: simulated .npz files, their LBS baselines, dataset stores.

A :class:`GarmentSequence` holds what :func:`simgen.physics.evaluate.evaluate_sequence` needs: the
garment positions (T, V, 3), the posed body (T, Vb, 3) and its root joint (T, 3), the frame rate, the
garment (rest shape and skinning weights), the material and the contact parameters it was simulated
with, and the body's skinning transforms (T, 24, 4, 4) from which :meth:`GarmentSequence.lbs` poses
the LBS baseline. Model predictions need no loader: pass their arrays to ``evaluate_sequence``.

- :func:`load_simulation`: an .npz written by :meth:`simgen.sim.SimulationResult.save_npz` (``simgen
  simulate``) or by scripts/sim_library.py. The body is re-posed from the library clip named in the
  metadata with its betas, at output frame k's time k / fps (the solver's poses: slerped joint
  rotations, linear root translation), unless the file stores body_vertices (then those are used).
- :func:`load_dataset_sequences`: the sequences of a dataset store (all or one split), the body posed
  from each sequence's stored poses, trans and betas.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from simgen.errors import InputError
from simgen.params import ContactParams

__all__ = ["GarmentSequence", "load_simulation", "load_dataset_sequences", "contact_params_from"]


def contact_params_from(solver: dict | None) -> ContactParams:
    """The ContactParams recorded in a solver config dict (SolverConfig as a dict); defaults if absent."""
    c = (solver or {}).get("contact")
    if not isinstance(c, dict):
        return ContactParams()
    known = {k: c[k] for k in ("margin", "stiffness", "power", "query_distance") if k in c}
    return ContactParams(**known)


@dataclass
class GarmentSequence:
    """One garment sequence on a posed body (numpy; shapes as in the module doc).

    name: label; positions [m] (T, V, 3); fps [1/s]; garment: the :class:`simgen.garment.Garment`
    (rest shape, faces, skinning weights); material: :class:`simgen.sim.Material`; contact: the
    ContactParams it was simulated with; body: the BodyModel; betas (B,) or (T, B); body_vertices [m]
    (T, Vb, 3); root [m] (T, 3); transforms (T, 24, 4, 4); meta: free-form (motion, source file ...).
    """

    name: str
    positions: np.ndarray
    fps: float
    garment: object
    material: object
    contact: ContactParams
    body: object
    betas: np.ndarray
    body_vertices: np.ndarray
    root: np.ndarray
    transforms: np.ndarray
    meta: dict = field(default_factory=dict)

    @property
    def num_frames(self) -> int:
        return int(self.positions.shape[0])

    def lbs(self, *, shape_method: str = "diffused") -> "GarmentSequence":
        """The LBS baseline of this sequence: the garment template moved to the shaped body
        (:func:`simgen.garment.skinning.shape_offsets`) and skinned with its weights by the body's
        transforms of every frame (no physics). Same body, fps, material and contact."""
        from simgen.garment.skinning import lbs, shape_offsets

        b = np.asarray(self.betas, dtype=np.float64)
        b = b if b.ndim == 1 else b[0]
        rest = self.garment.vertices + shape_offsets(self.garment.vertices, self.body, b[None], method=shape_method)[0]
        posed = lbs(rest, self.garment.skin_weights, self.transforms).astype(np.float32)
        return replace(self, name=f"{self.name} (LBS)", positions=posed, meta={**self.meta, "kind": "lbs"})

    def rest(self, *, material=None, bending_rest: str = "template", dtype=None, device=None):
        """The :class:`simgen.physics.ClothRest` of the garment (the solver's rest state; material
        default: the sequence's)."""
        import torch

        from simgen.physics.rest import ClothRest

        return ClothRest.from_garment(self.garment, material if material is not None else self.material,
                                      bending_rest=bending_rest, dtype=dtype or torch.float64, device=device)


def _pose_body(body, betas, poses, trans):
    """(vertices (T, Vb, 3) f4, root joint (T, 3), transforms (T, 24, 4, 4)) of the posed body."""
    out = body.forward_sequence(betas, poses, trans)
    return out.vertices, out.joints[:, 0].astype(np.float64), out.transforms


def _resolve_body(body):
    from simgen import body as body_pkg

    return body_pkg.load("open") if body is None else (body_pkg.load(body) if isinstance(body, str) else body)


def _read_simulation_npz(path: Path):
    """positions (T, V, 3) float32 [m], faces (F, 3), fps, body_vertices (T, Vb, 3) or None, and the
    metadata dict of a simulation .npz; InputError naming the file when it is missing, not a
    readable .npz (a truncated or corrupt archive included) or not a simulation output."""
    import tokenize
    import zipfile
    import zlib

    if not path.is_file():
        raise InputError(f"{path}: no such file")
    try:
        with np.load(path, allow_pickle=False) as data:
            keys = set(data.files)
            if "positions" not in keys or "faces" not in keys or "fps" not in keys:
                raise InputError(f"{path} is not a simulation output (needs arrays positions, faces and fps)")
            positions = data["positions"].astype(np.float32)
            faces = data["faces"]
            fps = float(data["fps"])
            stored_body = data["body_vertices"].astype(np.float32) if "body_vertices" in keys else None
            if "metadata" in keys:
                meta = json.loads(str(data["metadata"]))
            elif "summary" in keys and "motion" in keys:      # scripts/sim_library.py
                meta = json.loads(str(data["summary"]))
                meta["motion"] = str(data["motion"])
            else:
                raise InputError(f"{path} has no metadata (garment, motion): write it with SimulationResult.save_npz")
    except InputError:
        raise
    except (OSError, ValueError, EOFError, SyntaxError, tokenize.TokenError, zipfile.BadZipFile, zlib.error) as exc:
        # numpy parses a member's header with ast: a corrupt header raises SyntaxError or TokenError.
        raise InputError(f"{path} is not a readable .npz file ({exc})") from None
    return positions, faces, fps, stored_body, meta


def load_simulation(path, *, body=None, material=None) -> GarmentSequence:
    """A simulated sequence from an .npz (module doc).

    body: the BodyModel (or a body name; default "open"); material: override the recorded material
    (a preset name or Material). InputError for files that are not simulation outputs.
    """
    from simgen.garment.library import load_garment
    from simgen.motion.library import load_motion
    from simgen.motion.ops import poses_at
    from simgen.materials import Material, get_material

    path = Path(path)
    positions, faces, fps, stored_body, meta = _read_simulation_npz(path)
    for key in ("garment", "motion"):
        if not isinstance(meta.get(key), str):
            raise InputError(f"{path}: metadata lacks the {key} name")
    body = _resolve_body(body)
    garment = load_garment(meta["garment"], body=body)
    if garment.num_vertices != positions.shape[1] or not np.array_equal(np.asarray(garment.faces), faces):
        raise InputError(f"{path}: its mesh ({positions.shape[1]} vertices) is not garment {meta['garment']!r} "
                         f"({garment.num_vertices} vertices) as found for body {body.name!r}")
    if material is not None:
        mat = get_material(material)
    elif isinstance(meta.get("material"), dict):
        mat = Material.from_dict(meta["material"])
    else:
        mat = get_material((garment.metadata or {}).get("default_material") or "cotton")
    clip = load_motion(meta["motion"])
    betas = body.check_betas(np.asarray(meta.get("betas") or [0.0]))[0]
    T = positions.shape[0]
    poses, trans = poses_at(clip, np.arange(T) / fps)
    verts, root, transforms = _pose_body(body, betas, poses, trans)
    if stored_body is not None:
        if stored_body.shape != verts.shape:
            raise InputError(f"{path}: body_vertices has shape {stored_body.shape}, expected {verts.shape}")
        verts = stored_body
    return GarmentSequence(
        name=path.stem, positions=positions, fps=fps, garment=garment, material=mat,
        contact=contact_params_from(meta.get("solver")), body=body, betas=betas, body_vertices=verts, root=root,
        transforms=transforms, meta={"source": str(path), "motion": meta["motion"], "garment": meta["garment"],
                                     "kind": "simulation"})


def load_dataset_sequences(path, *, split: str | None = None, body=None, material=None,
                           limit: int | None = None) -> list[GarmentSequence]:
    """The sequences of a dataset store (``simgen.dataset.open_dataset``), all or one split.

    body: the BodyModel (default: the store's recorded body, checked against its hash); material:
    override the store's material; limit: at most this many sequences (in id order).
    """
    try:
        from simgen.dataset import open_dataset
    except ImportError as exc:  # the dataset package is optional at this layer
        raise InputError(f"reading dataset stores needs simgen.dataset ({exc})") from None
    from simgen.garment.garment import Garment
    from simgen.garment.library import load_garment
    from simgen.materials import get_material

    ds = open_dataset(path)
    b = ds.load_body(body) if hasattr(ds, "load_body") else _resolve_body(body)
    ids = ds.sequence_ids(split)
    if not ids:
        raise InputError(f"dataset {path} has no sequence" + (f" in split {split!r}" if split else ""))
    if limit is not None:
        ids = ids[:int(limit)]
    tpl = ds.template
    # The cloth's rest shape is the garment template the solver used (not the relaxed T_r).
    if "garment_template" in tpl:
        garment = Garment(name=ds.garment_name, vertices=np.asarray(tpl["garment_template"], dtype=np.float64),
                          faces=np.asarray(tpl["faces"]),
                          skin_weights=np.asarray(tpl["skin_weights"], dtype=np.float64),
                          metadata={})
    else:
        garment = load_garment(ds.garment_name, body=b)
    mat = get_material(material) if material is not None else ds.material
    attrs = ds.attrs
    solver = attrs.get("solver", {})
    contact = contact_params_from(solver.get("config", solver))
    out = []
    for seq_id in ids:
        seq = ds.sequence(seq_id)
        a = seq["attrs"]
        fps = float(a.get("fps") or solver.get("fps"))
        positions = np.asarray(seq["garment_vertices"], dtype=np.float32)
        if positions.shape[1] != garment.num_vertices:
            raise InputError(f"dataset {path}: sequence {seq_id} has {positions.shape[1]} vertices, the garment "
                             f"{garment.num_vertices}")
        betas = np.asarray(seq["betas"], dtype=np.float64)
        verts, root, transforms = _pose_body(b, betas, seq["poses"], seq["trans"])
        out.append(GarmentSequence(
            name=seq_id, positions=positions, fps=fps, garment=garment, material=mat, contact=contact, body=b,
            betas=betas, body_vertices=verts, root=root, transforms=transforms,
            meta={"source": str(path), "motion": a.get("motion"), "split": a.get("split"), "kind": "dataset"}))
    return out
