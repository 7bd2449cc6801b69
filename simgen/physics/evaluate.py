"""Physics evaluation of garment sequences: the SNUG terms per frame (thesis Fig. 5.4, Table 5.1).

:func:`evaluate_sequence` takes any garment sequence, positions [m] (T, V, 3) with the posed body
(T, Vb, 3) — a simulation, its LBS baseline, a dataset sequence, a model's prediction — and returns a
:class:`PhysicsReport` of per-frame values:

    strain      StVK membrane energy [J]               (eqs. 5.8-5.9)
    bending     dihedral bending energy [J]            (eq. 5.10)
    gravity     gravity potential [J]                  (eq. 5.11; datum: the floor, or the root joint)
    inertia     1/(2 h^2) |x - x_hat|_M^2 [J]          (eq. 5.6, h = 1/fps, x_hat from the sequence's own
                                                        two previous frames; NaN for frames 0 and 1)
    collision   k max(margin - d, 0)^p [J]             (eq. 5.12, the solver's contact term)
    potential   inertia + strain + bending + gravity + collision [J] (eq. 5.4's objective)
    inside_share  share of garment vertices with d < 0 (inside the body) [-]
    crossing_edges  garment edges that pass through a garment triangle (cloth through itself;
                  :mod:`simgen.garment.crossings`, float64, every frame) [-]

Every energy is a sum over the garment's elements at one frame (joules per frame); a report's
``means()`` averages over frames (NaN frames left out). ``normalisation`` rescales the energies:
"frame" (J per frame, the default), "vertex" (J per vertex per frame, divided by V), "area" (J per m^2
of rest garment, divided by the rest area: comparable across mesh resolutions), "snug" (J per frame
with gravity measured from the body's root joint height, the closest match to SNUG's body-centred
numbers, see docs/physics.md).

:func:`compare_potentials` measures the incremental potential of a candidate frame (e.g. LBS) and of
the reference (simulated) frame with the same history, the reference's two previous frames.
"""

from __future__ import annotations

import csv
import io
import math
from dataclasses import dataclass, field

import numpy as np
import torch

from simgen.errors import InputError
from simgen.physics.bending import bending
from simgen.physics.contact import contact
from simgen.physics.gravity import gravity
from simgen.physics.inertia import inertia, predict
from simgen.physics.membrane import membrane
from simgen.physics.rest import ClothRest
from simgen.physics.surface_query import BodySurface, body_distance
from simgen.params import ContactParams, GravityParams

__all__ = ["PhysicsReport", "evaluate_sequence", "compare_potentials", "write_csv", "COLUMNS", "ENERGY_COLUMNS",
           "NORMALISATIONS", "UNITS"]

ENERGY_COLUMNS = ("strain", "bending", "gravity", "inertia", "collision", "potential")
COLUMNS = ENERGY_COLUMNS + ("inside_share", "crossing_edges")
NORMALISATIONS = ("frame", "vertex", "area", "snug")
UNITS = {"frame": "J", "vertex": "J/vertex", "area": "J/m^2", "snug": "J"}


@dataclass
class PhysicsReport:
    """Per-frame physics terms of one garment sequence.

    name: label; fps [1/s]; values: {column: (T,) float64} (COLUMNS; NaN where undefined);
    normalisation: one of NORMALISATIONS (energies in UNITS[normalisation]); meta: free-form info
    (garment, motion, contact parameters, material ...).
    """

    name: str
    fps: float
    values: dict
    normalisation: str = "frame"
    meta: dict = field(default_factory=dict)

    @property
    def num_frames(self) -> int:
        return int(len(next(iter(self.values.values()))))

    @property
    def unit(self) -> str:
        return UNITS[self.normalisation]

    def means(self) -> dict:
        """Mean over frames of every column (frames where a value is NaN are left out)."""
        out = {}
        for k, v in self.values.items():
            v = np.asarray(v, dtype=np.float64)
            ok = np.isfinite(v)
            out[k] = float(v[ok].mean()) if ok.any() else float("nan")
        return out

    def csv_rows(self) -> list[dict]:
        """One dict per frame: source, frame, time [s] and every column."""
        rows = []
        for t in range(self.num_frames):
            row = {"source": self.name, "frame": t, "time": t / self.fps}
            row.update({k: float(v[t]) for k, v in self.values.items()})
            rows.append(row)
        return rows


def _normalise(values: dict, rest: ClothRest, normalisation: str) -> dict:
    if normalisation in ("frame", "snug"):
        return values
    div = rest.num_vertices if normalisation == "vertex" else rest.total_area
    return {k: (v / div if k in ENERGY_COLUMNS else v) for k, v in values.items()}


def _as_tensor(a, dtype, device) -> torch.Tensor:
    return torch.as_tensor(np.asarray(a), dtype=dtype, device=device)


def _check_sequence(positions, body_vertices, rest: ClothRest, surface: BodySurface, fps: float):
    pos = np.asarray(positions)
    bv = np.asarray(body_vertices)
    if pos.ndim != 3 or pos.shape[1:] != (rest.num_vertices, 3):
        raise InputError(f"garment positions must have shape (T, {rest.num_vertices}, 3), got {pos.shape}")
    if bv.ndim != 3 or bv.shape[0] != pos.shape[0] or bv.shape[2] != 3 or bv.shape[1] != surface.num_vertices:
        raise InputError(f"body vertices must have shape ({pos.shape[0]}, {surface.num_vertices}, 3), got {bv.shape}")
    if not np.all(np.isfinite(pos)):
        bad = int(np.flatnonzero(~np.isfinite(pos).all(axis=(1, 2)))[0])
        raise InputError(f"garment positions contain NaN or inf (first at frame {bad})")
    if not (isinstance(fps, (int, float)) and math.isfinite(fps) and fps > 0):
        raise InputError(f"fps must be a finite number > 0, got {fps!r}")
    return pos, bv


def _crossing_edges(positions: np.ndarray, faces, device: torch.device) -> np.ndarray:
    """Crossing edges per frame (T,) float64 of positions [m] (T, V, 3), counted on the torch
    ``device``'s GPU or on the CPU (Warp, loaded here only)."""
    from simgen._warp_log import init_warp
    from simgen.garment.crossings import count_crossing_edges

    f = faces.cpu().numpy() if isinstance(faces, torch.Tensor) else np.asarray(faces)
    wp_device = f"cuda:{device.index or 0}" if device.type == "cuda" else "cpu"
    init_warp(wp_device)
    return count_crossing_edges(positions, f, wp_device).astype(np.float64)


def evaluate_sequence(positions, body_vertices, rest: ClothRest, surface: BodySurface, fps: float, *,
                      contact_params: ContactParams = ContactParams(), gravity_params: GravityParams = GravityParams(),
                      root=None, normalisation: str = "frame", name: str = "sequence", meta: dict | None = None,
                      dtype: torch.dtype = torch.float64, device=None, chunk: int = 16,
                      progress=None) -> PhysicsReport:
    """Per-frame SNUG terms of one garment sequence (module doc).

    positions [m] (T, V, 3) and body_vertices [m] (T, Vb, 3): numpy or torch; rest: the garment's
    :class:`ClothRest` (its template and material: the solver's rest state); surface: the body's
    :class:`BodySurface`; fps [1/s]: frame rate (inertia's h = 1/fps); contact_params: the collision
    term's parameters (the solver's, ContactParams(), by default; ContactParams.snug() for SNUG's);
    root [m] (T, 3): root joint positions, required for normalisation "snug" (gravity datum);
    dtype/device: where the terms are computed (float64 on the CPU by default); chunk: frames per
    batch; progress: optional callable(done_frames, total_frames).
    """
    if normalisation not in NORMALISATIONS:
        raise InputError(f"normalisation must be one of {NORMALISATIONS}, got {normalisation!r}")
    if normalisation == "snug" and root is None:
        raise InputError("normalisation 'snug' needs the root joint positions (root=) for the gravity datum")
    pos, bv = _check_sequence(positions, body_vertices, rest, surface, fps)
    device = torch.device(device) if device is not None else rest.device
    r = rest.to(dtype=dtype, device=device)
    surface.to(device)
    T = pos.shape[0]
    dt = 1.0 / float(fps)
    cols = {k: np.full(T, np.nan) for k in COLUMNS}
    with torch.no_grad():
        for start in range(0, T, chunk):
            sl = slice(start, min(start + chunk, T))
            x = _as_tensor(pos[sl], dtype, device)
            b = _as_tensor(bv[sl], dtype, device)
            origin = None if normalisation != "snug" else _as_tensor(np.asarray(root)[sl], dtype, device)
            dist = body_distance(x, b, surface)
            values = {
                "strain": membrane(x, r, reduction="none"),
                "bending": bending(x, r, reduction="none"),
                "gravity": gravity(x, r, gravity_params, origin=origin, reduction="none"),
                "collision": contact(x, b, surface, contact_params, reduction="none", distance=dist),
                "inside_share": (dist.distance < 0).to(dtype).mean(-1),
            }
            for k, v in values.items():
                cols[k][sl] = v.cpu().numpy()
            # Inertia of frame t >= 2 against the sequence's own prediction 2 x_{t-1} - x_{t-2}.
            lo = max(sl.start, 2)
            if lo < sl.stop:
                xs = _as_tensor(pos[lo:sl.stop], dtype, device)
                x1 = _as_tensor(pos[lo - 1:sl.stop - 1], dtype, device)
                x2 = _as_tensor(pos[lo - 2:sl.stop - 2], dtype, device)
                cols["inertia"][lo:sl.stop] = inertia(xs, predict(x1, x2), r, dt, reduction="none").cpu().numpy()
            if progress is not None:
                progress(sl.stop, T)
    cols["potential"] = cols["inertia"] + cols["strain"] + cols["bending"] + cols["gravity"] + cols["collision"]
    cols["crossing_edges"] = _crossing_edges(pos, r.faces, device)
    info = dict(meta or {})
    info.update(contact=dict(margin=contact_params.margin, stiffness=contact_params.stiffness,
                             power=contact_params.power, query_distance=contact_params.query_distance),
                material=r.material.name if hasattr(r.material, "name") else str(r.material),
                bending_rest=r.bending_rest, vertices=r.num_vertices, rest_area=r.total_area, mass=r.total_mass)
    return PhysicsReport(name=name, fps=float(fps), values=_normalise(cols, r, normalisation),
                         normalisation=normalisation, meta=info)


def compare_potentials(reference, candidate, body_vertices, rest: ClothRest, surface: BodySurface, fps: float, *,
                       contact_params: ContactParams = ContactParams(), gravity_params: GravityParams = GravityParams(),
                       dtype: torch.dtype = torch.float64, device=None, chunk: int = 16, progress=None) -> dict:
    """Incremental potential (eq. 5.4) per frame of a reference sequence and of a candidate for the
    same frames, both with the reference's history.

    reference, candidate [m] (T, V, 3) (e.g. simulated and LBS); body_vertices [m] (T, Vb, 3).
    For frames t = 2..T-1: IP(x) = inertia(x; 2 r_{t-1} - r_{t-2}) + membrane + bending + gravity +
    contact, h = 1/fps. Returns {"frames": (T-2,) int, "reference": (T-2,) [J], "candidate": (T-2,) [J],
    "reference_terms" / "candidate_terms": {term: (T-2,)}, "lower_share": share of frames where the
    reference's IP is lower}.
    """
    ref, bv = _check_sequence(reference, body_vertices, rest, surface, fps)
    cand, _ = _check_sequence(candidate, body_vertices, rest, surface, fps)
    T = ref.shape[0]
    if T < 3:
        raise InputError(f"the incremental potential needs at least 3 frames, got {T}")
    device = torch.device(device) if device is not None else rest.device
    r = rest.to(dtype=dtype, device=device)
    surface.to(device)
    dt = 1.0 / float(fps)
    terms = ("inertia", "membrane", "bending", "gravity", "contact")
    out = {which: {k: np.zeros(T - 2) for k in terms} for which in ("reference", "candidate")}
    with torch.no_grad():
        for start in range(2, T, chunk):
            sl = slice(start, min(start + chunk, T))
            o = slice(sl.start - 2, sl.stop - 2)
            x_hat = predict(_as_tensor(ref[sl.start - 1:sl.stop - 1], dtype, device),
                            _as_tensor(ref[sl.start - 2:sl.stop - 2], dtype, device))
            b = _as_tensor(bv[sl], dtype, device)
            for which, seq in (("reference", ref), ("candidate", cand)):
                x = _as_tensor(seq[sl], dtype, device)
                vals = {"inertia": inertia(x, x_hat, r, dt, reduction="none"),
                        "membrane": membrane(x, r, reduction="none"),
                        "bending": bending(x, r, reduction="none"),
                        "gravity": gravity(x, r, gravity_params, reduction="none"),
                        "contact": contact(x, b, surface, contact_params, reduction="none")}
                for k, v in vals.items():
                    out[which][k][o] = v.cpu().numpy()
            if progress is not None:
                progress(sl.stop - 2, T - 2)
    ip_ref = sum(out["reference"].values())
    ip_cand = sum(out["candidate"].values())
    return {"frames": np.arange(2, T), "reference": ip_ref, "candidate": ip_cand,
            "reference_terms": out["reference"], "candidate_terms": out["candidate"],
            "lower_share": float(np.mean(ip_ref < ip_cand))}


def write_csv(reports: list[PhysicsReport]) -> bytes:
    """The per-frame rows of every report as CSV bytes (columns: source, frame, time, COLUMNS)."""
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=["source", "frame", "time", *COLUMNS], lineterminator="\n")
    writer.writeheader()
    for rep in reports:
        for row in rep.csv_rows():
            writer.writerow({k: (f"{v:.9g}" if isinstance(v, float) else v) for k, v in row.items()})
    return buf.getvalue().encode("utf-8")
