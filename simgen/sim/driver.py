"""simulate(): one garment on one animated SMPL-format body, with the thesis's start protocol.

The start protocol (Santesteban's thesis, section 4.3.1) gives the implicit solver a collision-free
initial state for any shape and pose:

1. relax: the garment starts at its template positions (made on the template body in rest pose,
   outside it) and settles on the template body (betas = 0, rest pose) for ``relax_frames``;
2. ramp: over ``ramp_frames`` the betas go linearly from 0 to the target and every joint rotation
   is slerped from the identity to the clip's first frame with the same linear fraction;
3. rest: the body holds the clip's first frame for ``rest_frames`` while the cloth settles;
4. animate: the clip plays; output frame k is the cloth at clip time k / fps.

The root translation is the clip's first-frame translation through phases 1 to 3 and the garment
starts shifted by it: a rigid offset that carries no physics and keeps the body from sliding
through the ramp.

Each frame of 1/fps seconds is split into ``substeps`` solver steps. At every substep the body is
posed on the device from joint rotations slerped at the substep's end time
(:func:`simgen.motion.ops.quats_at`, then :meth:`WarpBody.pose_from_quats`), copied into the
collider whose meshes are refit (never rebuilt), with body velocities (new - old) / dt, and the
solver takes one step (its own ``SolverConfig.substeps`` subdivides that step further, with the body
moving linearly). The solver's projection (``SolverConfig.project``) pushes any vertex found inside
the body back onto it after every step, so output frames are free of penetration except where the
posed body intersects itself.

Self-intersection rule: a cloth vertex inside the body (signed distance < 0) counts as *at a body
self-intersection* when its closest body point, moved ``self_intersection_probe`` (2 mm) outward
along the contact normal, is still inside the body by the generalised winding number (> 0.5). A
closest surface that is buried in another body part (arm in torso at the armpit, thigh in thigh
at the crotch) cannot be exited along its normal, and the projection cannot resolve such vertices.
"""

from __future__ import annotations

import json
import math
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import numpy as np
import warp as wp

from simgen.errors import InputError
from simgen.rotations import quat_slerp
from simgen.sim.collider import BodyCollider
from simgen.sim.materials import Material, get_material
from simgen.sim.model import ClothModel
from simgen.sim.solver import ImplicitSolver, SolverConfig

__all__ = ["SimulationConfig", "SimulationResult", "simulate", "PHASES", "FRAME_STAT_KEYS"]

PHASES = ("relax", "ramp", "rest", "animate")

# Per-frame statistics (each an array over frames in SimulationResult.stats / protocol_stats).
FRAME_STAT_KEYS = (
    "max_depth",                  # [m] deepest cloth vertex inside the body at the output frame (0 if none)
    "max_depth_regular",          # [m] the same over vertices not at a body self-intersection
    "inside_count",               # vertices inside the body at the output frame
    "inside_share",               # inside_count / V
    "self_intersection_count",    # inside vertices at a body self-intersection (module doc's rule)
    "depth_before_projection",    # [m] deepest vertex the solver's projections found over the frame
    "retries",                    # half-step retries of the solver's divergence guard
    "unresolved",                 # steps still failing the guard after every retry (finite)
    "newton_iterations",          # Newton iterations over the frame's substeps
    "cg_iterations",              # PCG iterations over the frame's substeps
    "wall_time",                  # [s] host wall time of the frame, statistics included
)


@dataclass(frozen=True)
class SimulationConfig:
    """Options of :func:`simulate` (SI units).

    fps [1/s]: output frame rate; None takes the clip's. The frame time step is 1 / fps.
    substeps: solver steps per frame (10 at 30 fps: dt = 3.33 ms, the thesis's ARCSim step); the body
      is re-posed from slerped joint rotations before each.
    solver: the :class:`SolverConfig`; default: one Newton iteration, projection 0.2 mm outside the
      body so projected vertices count as outside.
    material: preset name or :class:`Material`; None takes the garment's default_material, else cotton.
    material_overrides: Material fields to replace, e.g. ``{"area_density": 0.25}``.
    relax_frames, ramp_frames (>= 1), rest_frames: the start protocol's frame counts (module doc).
    self_intersection_probe [m]: outward offset of the self-intersection test (module doc).
    query_distance [m]: deepest penetration the statistics can see.
    record_body: keep the posed body vertices of every output frame (SimulationResult.body_vertices).
    device: Warp device (None: Warp's default).
    """

    fps: float | None = None
    substeps: int = 10
    solver: SolverConfig = field(default_factory=lambda: SolverConfig(projection_offset=2.0e-4))
    material: str | Material | None = None
    material_overrides: dict = field(default_factory=dict)
    relax_frames: int = 15
    ramp_frames: int = 30
    rest_frames: int = 15
    self_intersection_probe: float = 2.0e-3
    query_distance: float = 0.05
    record_body: bool = False
    device: str | None = None

    def __post_init__(self) -> None:
        if self.fps is not None and not (isinstance(self.fps, (int, float)) and not isinstance(self.fps, bool)
                                         and math.isfinite(self.fps) and self.fps > 0):
            raise InputError(f"simulation fps must be a finite number > 0 or None, got {self.fps!r}")
        for name, low in (("substeps", 1), ("relax_frames", 0), ("ramp_frames", 1), ("rest_frames", 0)):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < low:
                raise InputError(f"simulation {name} must be an integer >= {low}, got {v!r}")
        if not isinstance(self.solver, SolverConfig):
            raise InputError(f"simulation solver must be a SolverConfig, got {type(self.solver).__name__}")
        for name in ("self_intersection_probe", "query_distance"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not (math.isfinite(v) and v > 0):
                raise InputError(f"simulation {name} must be a finite number > 0, got {v!r}")
        if not isinstance(self.material_overrides, dict):
            raise InputError("simulation material_overrides must be a dict of Material fields")

    def resolve_material(self, garment=None) -> Material:
        """The Material this config simulates (preset or given, defaults from the garment, overrides applied)."""
        name = self.material
        if name is None:
            name = ((getattr(garment, "metadata", None) or {}).get("default_material")) or "cotton"
        material = get_material(name)
        if self.material_overrides:
            known = set(Material.__dataclass_fields__)
            bad = sorted(set(self.material_overrides) - known)
            if bad:
                raise InputError(f"unknown material fields {bad}; fields are: {', '.join(sorted(known))}")
            material = replace(material, **self.material_overrides)
        return material


@dataclass
class SimulationResult:
    """What :func:`simulate` returns.

    positions [m]: (T, V, 3) float32, the cloth at the clip's output frames only (frame k at clip
      time k / fps; frame 0 is the end of the protocol's rest phase, body at the clip's first frame).
    faces: (F, 3) int32 triangles of the garment.
    fps [1/s]; dt [s]: the solver substep.
    stats: dict of (T,) arrays, keys :data:`FRAME_STAT_KEYS` (units there).
    protocol_positions [m]: (P, V, 3) float32, the cloth at the end of each protocol frame
      (relax, ramp, rest, in order); protocol_phases: (P,) phase names; protocol_stats: as stats.
    body_vertices [m]: (T, Vb, 3) float32 posed body per output frame if config.record_body, else None.
    body_faces: (Fb, 3) int32 body triangles.
    metadata: JSON-serialisable run description (garment, body, motion, betas, material, configs,
      totals, initial_inside: template vertices found inside the template body and projected out).
    """

    positions: np.ndarray
    faces: np.ndarray
    fps: float
    dt: float
    stats: dict
    protocol_positions: np.ndarray
    protocol_phases: np.ndarray
    protocol_stats: dict
    body_vertices: np.ndarray | None
    body_faces: np.ndarray
    metadata: dict

    @property
    def num_frames(self) -> int:
        return int(self.positions.shape[0])

    def save_npz(self, path) -> Path:
        """Write everything to one compressed .npz (no USD needed; e.g. on the GPU machine).

        Arrays: positions (T, V, 3) f4, faces (F, 3) i4, fps, dt, stats_<key> (T,),
        protocol_positions (P, V, 3) f4, protocol_phases (P,) str, protocol_stats_<key> (P,),
        body_faces (Fb, 3) i4, body_vertices (T, Vb, 3) f4 when recorded, and metadata (a JSON string).
        Returns the path written.
        """
        path = Path(path)
        if path.suffix != ".npz":
            path = path.with_suffix(".npz")
        arrays = dict(positions=self.positions.astype(np.float32), faces=self.faces.astype(np.int32),
                      fps=np.float64(self.fps), dt=np.float64(self.dt),
                      protocol_positions=self.protocol_positions.astype(np.float32),
                      protocol_phases=np.asarray(self.protocol_phases, dtype=str),
                      body_faces=self.body_faces.astype(np.int32),
                      metadata=np.asarray(json.dumps(self.metadata)))
        for k, v in self.stats.items():
            arrays["stats_" + k] = np.asarray(v)
        for k, v in self.protocol_stats.items():
            arrays["protocol_stats_" + k] = np.asarray(v)
        if self.body_vertices is not None:
            arrays["body_vertices"] = self.body_vertices.astype(np.float32)
        path.parent.mkdir(parents=True, exist_ok=True)
        # Written under a temporary name and renamed, so a killed run leaves no half file.
        tmp = path.with_name(path.name + ".tmp.npz")
        np.savez_compressed(tmp, **arrays)
        tmp.replace(path)
        return path


# ------------------------------------------------------------------------------------ statistics
@wp.kernel(enable_backward=False)
def _classify_inside(
    x: wp.array(dtype=wp.vec3),
    winding_mesh: wp.uint64,
    query_distance: float,
    probe: float,
    depth: wp.array(dtype=wp.float32),
    inside: wp.array(dtype=wp.int32),
    self_hit: wp.array(dtype=wp.int32),
):
    # depth[i] = distance to the body surface if inside, else 0; self_hit[i] = 1 if inside at a
    # self-intersection. Inside/outside by the generalised winding number, which stays right
    # where body parts overlap (a normal-based sign there reads the other part's outside).
    i = wp.tid()
    depth[i] = 0.0
    inside[i] = 0
    self_hit[i] = 0
    xi = x[i]
    q = wp.mesh_query_point_sign_winding_number(winding_mesh, xi, query_distance, 2.0, 0.5)
    if not q.result or q.sign > 0.0:
        return
    p = wp.mesh_eval_position(winding_mesh, q.face, q.u, q.v)
    d = wp.length(p - xi)
    depth[i] = d
    inside[i] = 1
    n = wp.vec3(0.0)
    if d > 1.0e-9:
        n = (p - xi) / d
    else:
        a = wp.mesh_get_point(winding_mesh, q.face * 3 + 0)
        b = wp.mesh_get_point(winding_mesh, q.face * 3 + 1)
        c = wp.mesh_get_point(winding_mesh, q.face * 3 + 2)
        n = wp.normalize(wp.cross(b - a, c - a))
    w = wp.mesh_query_point_sign_winding_number(winding_mesh, p + probe * n, query_distance + probe, 2.0, 0.5)
    if w.result and w.sign < 0.0:
        self_hit[i] = 1


class _FrameStats:
    """Per-frame statistics of one instance: penetration at the output frame + solver counters."""

    def __init__(self, model: ClothModel, collider: BodyCollider, config: SimulationConfig) -> None:
        dev = model.device
        self.model, self.collider, self.config = model, collider, config
        n = model.num_vertices
        self.depth = wp.zeros(n, dtype=wp.float32, device=dev)
        self.inside = wp.zeros(n, dtype=wp.int32, device=dev)
        self.self_hit = wp.zeros(n, dtype=wp.int32, device=dev)
        # The collider's meshes lack winding-number support; a second BVH on the same points adds it
        # and is refit only when statistics are taken.
        nv = collider.num_body_vertices
        self.winding_mesh = wp.Mesh(points=collider.points[:nv], indices=collider.faces, support_winding_number=True)

    def measure(self, positions: wp.array) -> dict:
        self.winding_mesh.refit()
        cfg = self.config
        wp.launch(_classify_inside, dim=self.model.num_vertices, device=self.model.device,
                  inputs=[positions, self.winding_mesh.id, float(cfg.query_distance),
                          float(cfg.self_intersection_probe), self.depth, self.inside, self.self_hit])
        depth, inside, self_hit = self.depth.numpy(), self.inside.numpy(), self.self_hit.numpy()
        regular = (inside != 0) & (self_hit == 0)
        return dict(
            max_depth=float(depth.max(initial=0.0)),
            max_depth_regular=float(depth[regular].max(initial=0.0)),
            inside_count=int(inside.sum()),
            inside_share=float(inside.sum()) / len(inside),
            self_intersection_count=int(self_hit.sum()),
        )


def _stack_stats(rows: list[dict]) -> dict:
    out = {}
    for k in FRAME_STAT_KEYS:
        dtype = np.int64 if k in ("inside_count", "self_intersection_count", "retries", "unresolved",
                                  "newton_iterations", "cg_iterations") else np.float64
        out[k] = np.array([r[k] for r in rows], dtype=dtype)
    return out


# ------------------------------------------------------------------------------------ inputs
def _resolve_inputs(garment, body, clip):
    from simgen import body as body_pkg
    from simgen.body.model import BodyModel
    from simgen.garment.garment import Garment
    from simgen.garment.library import load_garment
    from simgen.motion.clip import MotionClip
    from simgen.motion.library import load_motion

    if isinstance(body, str):
        body = body_pkg.load(body)
    elif not isinstance(body, BodyModel):
        raise InputError(f"body must be a BodyModel or a body name, got {type(body).__name__}")
    if isinstance(garment, str):
        garment = load_garment(garment, body=body)
    elif not isinstance(garment, Garment):
        raise InputError(f"garment must be a Garment or a garment name, got {type(garment).__name__}")
    if isinstance(clip, str):
        clip = load_motion(clip)
    elif not isinstance(clip, MotionClip):
        raise InputError(f"clip must be a MotionClip or a motion name, got {type(clip).__name__}")
    return garment, body, clip


def _identity_quats(k: int) -> np.ndarray:
    q = np.zeros((k, 24, 4))
    q[..., 0] = 1.0
    return q


def _trans_at(clip, times: np.ndarray) -> np.ndarray:
    """Root translation [m] (K, 3) at times [s] (K,), linear between frames, clamped to the clip."""
    t = clip.times
    return np.stack([np.interp(times, t, clip.trans[:, c]) for c in range(3)], axis=1)


# ------------------------------------------------------------------------------------ simulate
def simulate(garment, body, clip, betas=None, config: SimulationConfig | None = None, *,
             frames: int | None = None, progress=None) -> SimulationResult:
    """Simulate ``garment`` on ``body`` shaped by ``betas`` doing ``clip``, after the start protocol.

    garment: :class:`simgen.garment.Garment` made on this body (or a library name); body:
      :class:`simgen.body.BodyModel` (or a body name, e.g. "open"); clip: :class:`MotionClip` (or a
      library name); betas: (B',) shape coefficients, B' <= the body's (None: zeros).
    config: :class:`SimulationConfig` (None: defaults).
    frames: output frames to simulate (default: the whole clip at config.fps); more than the clip
      holds repeat its last pose.
    progress: optional callable(done, total, phase) after each simulated frame (protocol included).
    Returns a :class:`SimulationResult`; positions hold the clip's frames only, protocol frames are
    in ``protocol_positions``. Raises :class:`simgen.sim.SolverDivergedError` if the cloth blows up.
    """
    from simgen.body.warp_lbs import WarpBody, quats_from_simgen
    from simgen.motion.ops import quats_at

    cfg = config if config is not None else SimulationConfig()
    if not isinstance(cfg, SimulationConfig):
        raise InputError(f"config must be a SimulationConfig, got {type(cfg).__name__}")
    garment, body, clip = _resolve_inputs(garment, body, clip)
    target_betas = np.zeros(body.num_betas) if betas is None else body.check_betas(betas).reshape(-1)
    fps = float(cfg.fps) if cfg.fps is not None else float(clip.fps)
    num_out = int(math.floor(clip.duration * fps + 1e-9)) + 1 if frames is None else frames
    if isinstance(num_out, bool) or not isinstance(num_out, (int, np.integer)) or num_out < 1:
        raise InputError(f"frames must be an integer >= 1, got {frames!r}")
    num_out = int(num_out)
    S = cfg.substeps
    frame_dt = 1.0 / fps
    h = frame_dt / S
    device = wp.get_device(cfg.device)
    material = cfg.resolve_material(garment)

    model = ClothModel.from_garment(garment, material, device=device)
    solver = ImplicitSolver(model, cfg.solver)
    nb = max(body.num_betas, 1)
    wbody = WarpBody(body, max_batch=1, device=device)
    # Per-frame device buffers: substep s poses from row s (views, no allocation in the loop).
    quats_dev = wp.zeros((S, 24), dtype=wp.quat, device=device)
    trans_dev = wp.zeros(S, dtype=wp.vec3, device=device)
    betas_dev = wp.zeros((S, nb), dtype=wp.float32, device=device)
    quat_rows = [quats_dev[s:s + 1] for s in range(S)]
    trans_rows = [trans_dev[s:s + 1] for s in range(S)]
    betas_rows = [betas_dev[s:s + 1] for s in range(S)]

    trans0 = clip.trans[0].astype(np.float64)
    q_first = quats_at(clip, np.array([0.0]))[0]                      # (24, 4) wxyz, w >= 0
    betas_full = np.zeros(nb)
    betas_full[:len(target_betas)] = target_betas

    # Template body at rest, translated to the clip's start; the garment rigidly with it.
    wbody.set_shape(np.zeros((1, body.num_betas)))
    quats_dev.assign(np.broadcast_to(quats_from_simgen(_identity_quats(1)), (S, 24, 4)))
    trans_dev.assign(np.broadcast_to(trans0.astype(np.float32), (S, 3)))
    wbody.pose_from_quats(quat_rows[0], trans_rows[0])
    collider = BodyCollider.from_warp_body(wbody, device=device)
    state = model.state()
    x0 = (np.asarray(garment.vertices, dtype=np.float64) + trans0).astype(np.float32)
    state.positions.assign(x0)
    state.velocities.zero_()
    stats_probe = _FrameStats(model, collider, cfg)
    initial = stats_probe.measure(state.positions)
    if initial["inside_count"]:
        # The garment must never start inside the body: project what a bad template left inside.
        collider.project(model, state, offset=cfg.solver.projection_offset, query_distance=cfg.query_distance)

    schedule = ([("relax", k) for k in range(cfg.relax_frames)] + [("ramp", k) for k in range(cfg.ramp_frames)]
                + [("rest", k) for k in range(cfg.rest_frames)] + [("animate", k) for k in range(num_out)])
    fractions = np.arange(1, S + 1) / S                                # substep end times within a frame

    def body_targets(phase: str, k: int):
        """Joint rotations wxyz (S, 24, 4), trans (S, 3) and betas (S, nb) at the frame's substep ends."""
        if phase == "relax":
            return _identity_quats(S), np.repeat(trans0[None], S, 0), np.zeros((S, nb))
        if phase == "ramp":
            u = (k + fractions) / cfg.ramp_frames                      # 0 -> 1 over the ramp, linear
            q = quat_slerp(_identity_quats(1), q_first[None], u[:, None] * np.ones((S, 24)))
            return q, np.repeat(trans0[None], S, 0), u[:, None] * betas_full[None]
        if phase == "rest":
            return np.repeat(q_first[None], S, 0), np.repeat(trans0[None], S, 0), np.repeat(betas_full[None], S, 0)
        # animate: output frame k is clip time k / fps; frame 0 is the rest phase's last state.
        times = (k - 1 + fractions) * frame_dt
        return quats_at(clip, times), _trans_at(clip, times), np.repeat(betas_full[None], S, 0)

    out_positions, out_stats, out_body = [], [], []
    proto_positions, proto_phases, proto_stats = [], [], []
    total = len(schedule)
    current_betas = np.zeros(nb)
    t_start = time.perf_counter()
    for done, (phase, k) in enumerate(schedule):
        t0 = time.perf_counter()
        solver.reset_stats()
        # Output frame 0 of the animation is the protocol's end state: no step, only statistics.
        if not (phase == "animate" and k == 0):
            q, tr, bt = body_targets(phase, k)
            quats_dev.assign(quats_from_simgen(q).reshape(S, 24, 4))
            trans_dev.assign(tr.astype(np.float32))
            # Re-shape only while the betas change (ramp), never for a shapeless body model.
            reshape = body.num_betas > 0 and not np.all(bt == current_betas[None])
            if reshape:
                betas_dev.assign(bt.astype(np.float32))
            for s in range(S):
                if reshape:
                    wbody.set_shape(betas_rows[s])
                wbody.pose_from_quats(quat_rows[s], trans_rows[s])
                collider.update(dt=h)
                solver.step(state, state, collider, h)
            current_betas = bt[-1].copy()
        row = stats_probe.measure(state.positions)
        st = solver.stats
        row.update(depth_before_projection=st["max_penetration"], retries=st["retries"],
                   unresolved=st["unresolved"], newton_iterations=st["newton_iterations"],
                   cg_iterations=st["cg_iterations"])
        x = state.positions.numpy().astype(np.float32)
        row["wall_time"] = time.perf_counter() - t0
        if phase == "animate":
            out_positions.append(x)
            out_stats.append(row)
            if cfg.record_body:
                out_body.append(wbody.vertices.numpy()[0].astype(np.float32))
        else:
            proto_positions.append(x)
            proto_phases.append(phase)
            proto_stats.append(row)
        if progress is not None:
            progress(done + 1, total, phase)
    wall = time.perf_counter() - t_start

    nv = model.num_vertices
    stats = _stack_stats(out_stats)
    metadata = dict(
        garment=garment.name, garment_vertices=int(nv), garment_triangles=int(len(garment.faces)),
        body=body.name, body_vertices=int(body.num_vertices), motion=clip.name, motion_fps=float(clip.fps),
        fps=fps, substeps=S, dt=h, frames=num_out, betas=[float(b) for b in target_betas],
        material=asdict(material),
        config=dict(relax_frames=cfg.relax_frames, ramp_frames=cfg.ramp_frames, rest_frames=cfg.rest_frames,
                    self_intersection_probe=cfg.self_intersection_probe, query_distance=cfg.query_distance,
                    device=str(device)),
        solver=json.loads(json.dumps(asdict(cfg.solver), default=float)),
        initial_inside=int(initial["inside_count"]),
        wall_time=wall,
        wall_time_per_frame=wall / total,
        max_depth_regular=float(stats["max_depth_regular"].max()),
        max_self_intersection_count=int(stats["self_intersection_count"].max()),
        retries=int(stats["retries"].sum() + sum(r["retries"] for r in proto_stats)),
    )
    V3 = (0, nv, 3)
    return SimulationResult(
        positions=np.stack(out_positions),
        faces=np.asarray(garment.faces, dtype=np.int32),
        fps=fps, dt=h, stats=stats,
        protocol_positions=np.stack(proto_positions) if proto_positions else np.zeros(V3, np.float32),
        protocol_phases=np.array(proto_phases, dtype=str),
        protocol_stats=_stack_stats(proto_stats) if proto_stats else {k: np.zeros(0) for k in FRAME_STAT_KEYS},
        body_vertices=np.stack(out_body) if cfg.record_body else None,
        body_faces=wbody.faces.numpy().reshape(-1, 3).astype(np.int32),
        metadata=metadata,
    )
