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

The per-frame statistics (penetration, body self-intersections, whether the garment is on the
body) are taken by :class:`simgen.sim.frame_stats.FrameStats`.
"""

from __future__ import annotations

import json
import math
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np
import warp as wp

from simgen.errors import InputError
from simgen.rotations import quat_slerp
from simgen.sim.collider import BodyCollider
from simgen.sim.frame_stats import FRAME_STAT_KEYS, FrameStats, stack_stats
from simgen.materials import Material, get_material
from simgen.sim.model import ClothModel
from simgen.sim.config import SimulationConfig
from simgen.sim.solver import ImplicitSolver

__all__ = ["SimulationConfig", "SimulationResult", "SimulationJob", "SimulationFailure", "simulate",
           "simulate_batch", "PHASES", "FRAME_STAT_KEYS"]

PHASES = ("relax", "ramp", "rest", "animate")

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


# ------------------------------------------------------------------------------------ kernels
@wp.kernel(enable_backward=False)
def _hold_instances(pinned_before: wp.array(dtype=wp.int32), vertex_instance: wp.array(dtype=wp.int32),
                    held: wp.array(dtype=wp.int32), pinned: wp.array(dtype=wp.int32), v: wp.array(dtype=wp.vec3)):
    # Held instances are pinned with zero velocity (kinematic and still); the others keep their pins.
    i = wp.tid()
    if held[vertex_instance[i]] != 0:
        pinned[i] = 1
        v[i] = wp.vec3(0.0)
    else:
        pinned[i] = pinned_before[i]


@wp.kernel(enable_backward=False)
def _select_instances(src_x: wp.array(dtype=wp.vec3), src_v: wp.array(dtype=wp.vec3),
                      vertex_instance: wp.array(dtype=wp.int32), chosen: wp.array(dtype=wp.int32),
                      x: wp.array(dtype=wp.vec3), v: wp.array(dtype=wp.vec3)):
    i = wp.tid()
    if chosen[vertex_instance[i]] != 0:
        x[i] = src_x[i]
        v[i] = src_v[i]



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
@dataclass(frozen=True)
class SimulationJob:
    """One instance of :func:`simulate_batch`.

    clip: :class:`MotionClip` or a library motion name; betas: (B',) shape coefficients (None:
    zeros); frames: output frames (None: the whole clip; more than it holds repeat its last pose);
    key: a label carried into the result's metadata and into failures (default: the job's index);
    material: preset name or :class:`Material` (None: the config's, with its overrides).
    """

    clip: object
    betas: object = None
    frames: int | None = None
    key: str | None = None
    material: str | Material | None = None


@dataclass
class SimulationFailure:
    """The slot of a :func:`simulate_batch` instance that diverged: its key, the reason, and where
    (``phase`` of the start protocol or "animate", ``frame`` index within that phase)."""

    key: str
    message: str
    phase: str
    frame: int


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
    This is :func:`simulate_batch` with one job.
    """
    (result,) = simulate_batch(garment, body, [SimulationJob(clip, betas=betas, frames=frames)], config,
                               progress=progress)
    if isinstance(result, SimulationFailure):
        from simgen.sim.solver import SolverDivergedError

        raise SolverDivergedError(f"{result.message} (phase {result.phase}, frame {result.frame})", instances=[0])
    return result


def _check_frames(frames) -> None:
    if frames is not None and (isinstance(frames, bool) or not isinstance(frames, (int, np.integer)) or frames < 1):
        raise InputError(f"frames must be an integer >= 1, got {frames!r}")


def simulate_batch(garment, body, jobs, config: SimulationConfig | None = None, *,
                   progress=None) -> list:
    """Simulate N jobs of one garment on one body model as one batched system.

    Every :class:`SimulationJob` is its own instance (garment copy, material, body shape, motion) of
    one :class:`ClothModel` with N instances and one posed body mesh each; all step together
    through the start protocol and the animation (:func:`simulate` describes both).
    Clips of unequal length share the batch: it runs to the longest job, a shorter clip holds its
    last pose meanwhile, and each result is cut to its own frames. All clips must share one frame
    rate (config.fps, or the clips' own when it is None).

    On CUDA each frame's substeps (body posing, refits, solver) replay as one captured CUDA graph
    (``config.cuda_graph``); the CPU runs the same sequence uncaptured. The solver's guard runs
    inside and is read once per frame: the instances that failed it are redone from the frame's
    start with every substep split into 2, then 4, ... solver steps (up to the solver's
    ``max_retries`` levels, each level its own captured graph) while the others are held where
    they got, so no instance's result depends on its batch mates' failures and a retry costs one
    finer frame, not an uncaptured one. An instance still not finite after the last level is
    frozen (back at the frame start, pinned, its body switched off) and its slot returns a
    :class:`SimulationFailure`; the others go on.

    progress: optional callable(done, total, phase) after each batch frame (protocol included).
    Returns one :class:`SimulationResult` or :class:`SimulationFailure` per job, in order.
    """
    from simgen.body.warp_lbs import WarpBody, quats_from_simgen
    from simgen.motion.library import load_motion
    from simgen.motion.ops import quats_at
    from simgen.motion.clip import MotionClip

    cfg = config if config is not None else SimulationConfig()
    if not isinstance(cfg, SimulationConfig):
        raise InputError(f"config must be a SimulationConfig, got {type(cfg).__name__}")
    jobs = list(jobs)
    if not jobs:
        raise InputError("simulate_batch needs at least one SimulationJob")
    for i, job in enumerate(jobs):
        if not isinstance(job, SimulationJob):
            raise InputError(f"job {i} must be a SimulationJob, got {type(job).__name__}")
        _check_frames(job.frames)
    garment, body, _ = _resolve_inputs(garment, body, jobs[0].clip)
    clips_by_name: dict = {}

    def clip_of(c):
        if isinstance(c, str):
            if c not in clips_by_name:
                clips_by_name[c] = load_motion(c)
            return clips_by_name[c]
        if not isinstance(c, MotionClip):
            raise InputError(f"clip must be a MotionClip or a motion name, got {type(c).__name__}")
        return c

    clips = [clip_of(j.clip) for j in jobs]
    keys = [str(j.key) if j.key is not None else str(i) for i, j in enumerate(jobs)]
    if cfg.fps is None and len({float(c.fps) for c in clips}) > 1:
        raise InputError("the clips of one batch have different frame rates "
                         f"({sorted({float(c.fps) for c in clips})}); set SimulationConfig.fps")
    fps = float(cfg.fps) if cfg.fps is not None else float(clips[0].fps)
    num_out = [int(math.floor(c.duration * fps + 1e-9)) + 1 if j.frames is None else int(j.frames)
               for j, c in zip(jobs, clips)]
    target_betas = [np.zeros(body.num_betas) if j.betas is None else body.check_betas(j.betas).reshape(-1)
                    for j in jobs]
    N, S = len(jobs), cfg.substeps
    frame_dt = 1.0 / fps
    h = frame_dt / S
    device = wp.get_device(cfg.device)
    materials = [cfg.resolve_material(garment) if j.material is None
                 else replace(get_material(j.material), **cfg.material_overrides) for j in jobs]

    # One model instance per job; jobs with equal materials reuse one built instance.
    built: list = []
    for mat in materials:
        if not any(m == mat for m, _ in built):
            built.append((mat, ClothModel.from_garment(garment, mat, body=body, device=device)))
    parts = [next(mdl for m, mdl in built if m == mat) for mat in materials]
    model = parts[0] if N == 1 else ClothModel.concatenate(parts)
    starts = np.asarray(model.vertex_start)
    nv = garment.num_vertices
    solver = ImplicitSolver(model, cfg.solver)
    nb = max(body.num_betas, 1)
    wbody = WarpBody(body, max_batch=N, device=device)
    # Per-frame device buffers, substep s poses from row s (views, no allocation in the loop).
    quats_dev = wp.zeros((S, N, 24), dtype=wp.quat, device=device)
    trans_dev = wp.zeros((S, N), dtype=wp.vec3, device=device)
    betas_dev = wp.zeros((S, N, nb), dtype=wp.float32, device=device)
    quat_rows = [quats_dev[s] for s in range(S)]
    trans_rows = [trans_dev[s] for s in range(S)]
    betas_rows = [betas_dev[s] for s in range(S)]

    trans0 = np.stack([c.trans[0].astype(np.float64) for c in clips])              # (N, 3)
    q_first = np.stack([quats_at(c, np.array([0.0]))[0] for c in clips])          # (N, 24, 4) wxyz
    betas_full = np.zeros((N, nb))
    for i, b in enumerate(target_betas):
        betas_full[i, :len(b)] = b
    identity = quats_from_simgen(_identity_quats(1))[0].astype(np.float32)       # (24, 4) xyzw

    # Template body at rest, translated to each clip's start; each garment rigidly with it.
    wbody.set_shape(np.zeros((1, body.num_betas)), num_instances=N)
    quats_dev.assign(np.broadcast_to(identity, (S, N, 24, 4)))
    trans_dev.assign(np.broadcast_to(trans0.astype(np.float32), (S, N, 3)))
    wbody.pose_from_quats(quat_rows[0], trans_rows[0])
    collider = BodyCollider.from_warp_body(wbody, device=device)
    state = model.state()
    x0 = (np.asarray(garment.vertices, dtype=np.float64)[None] + trans0[:, None]).astype(np.float32)
    state.positions.assign(x0.reshape(-1, 3))
    state.velocities.zero_()
    stats_probe = FrameStats(model, collider, wbody, garment, body, query_distance=cfg.query_distance,
                             self_intersection_probe=cfg.self_intersection_probe,
                             pinch_distance=cfg.solver.contact.pinch_distance)
    initial = stats_probe.measure(state.positions, np.zeros((N, nb)))
    if any(r["inside_count"] for r in initial):
        # The garment must never start inside the body: project what a bad template left inside.
        collider.project(model, state, offset=cfg.solver.projection_offset, query_distance=cfg.query_distance,
                         pinch_distance=cfg.solver.contact.pinch_distance)

    T_max = max(num_out)
    schedule = ([("relax", k) for k in range(cfg.relax_frames)] + [("ramp", k) for k in range(cfg.ramp_frames)]
                + [("rest", k) for k in range(cfg.rest_frames)] + [("animate", k) for k in range(T_max)])
    fractions = np.arange(1, S + 1) / S                                           # substep ends in a frame
    # Animation targets of every job, precomputed over its whole clip (one slerp call each).
    anim_times = ((np.arange(max(T_max - 1, 0))[:, None] + fractions[None]) * frame_dt).reshape(-1)
    anim_quats = [quats_from_simgen(quats_at(c, np.minimum(anim_times, c.duration))).astype(np.float32)
                  .reshape(-1, S, 24, 4) for c in clips]
    anim_trans = [_trans_at(c, anim_times).astype(np.float32).reshape(-1, S, 3) for c in clips]

    def body_targets(phase: str, k: int):
        """Joint rotations xyzw (S, N, 24, 4), trans (S, N, 3) and betas (S, N, nb) at the frame's substep ends."""
        tr = np.broadcast_to(trans0[None], (S, N, 3))
        if phase == "relax":
            return np.broadcast_to(identity, (S, N, 24, 4)), tr, np.zeros((S, N, nb))
        if phase == "ramp":
            u = (k + fractions) / cfg.ramp_frames                                  # 0 -> 1, linear
            q = quat_slerp(_identity_quats(1)[None], q_first[None], u[:, None, None] * np.ones((S, N, 24)))
            return quats_from_simgen(q), tr, u[:, None, None] * betas_full[None]
        if phase == "rest":
            q = quats_from_simgen(q_first)
            return np.broadcast_to(q[None], (S, N, 24, 4)), tr, np.broadcast_to(betas_full[None], (S, N, nb))
        # animate: output frame k is clip time k / fps; frame 0 is the rest phase's last state.
        return (np.stack([a[k - 1] for a in anim_quats], axis=1), np.stack([a[k - 1] for a in anim_trans], axis=1),
                np.broadcast_to(betas_full[None], (S, N, nb)))

    # -- one frame: S substeps of posing, refit and solver step; eager or as a CUDA graph ----------
    use_graph = bool(cfg.cuda_graph) and device.is_cuda
    graphs: dict = {}
    frame_backup = model.state()
    accepted = model.state()
    body_backup = wp.clone(collider.points)
    held = wp.zeros(N, dtype=wp.int32, device=device)
    max_level = cfg.solver.max_retries if cfg.solver.guard else 0

    def run_substeps(reshape: bool, level: int) -> None:
        solver.clear_deferred_guard()
        if level > 0:
            # A retry starts from the restored frame start: friction's contacts are taken there
            # (at capture this puts their update into the retry's graph).
            solver.reset_contacts()
        for s in range(S):
            if reshape:
                wbody.set_shape(betas_rows[s])
            wbody.pose_from_quats(quat_rows[s], trans_rows[s])
            collider.update(dt=h)
            solver.step(state, state, collider, h, deferred_guard=True,
                        substeps=cfg.solver.substeps * 2 ** level)

    def attempt(reshape: bool, level: int, eager: bool) -> np.ndarray:
        """Run the frame's substeps (each split into 2^level solver steps); the guard's bits per instance."""
        if eager:
            run_substeps(reshape, level)
        else:
            key = (reshape, level)
            if key not in graphs:
                before = solver.host_counts()
                with wp.ScopedCapture(device=device, force_module_load=False) as capture:
                    run_substeps(reshape, level)
                after = solver.host_counts()
                graphs[key] = (capture.graph, {c: after[c] - before[c] for c in after})
                solver.add_host_counts({c: -v for c, v in graphs[key][1].items()})
            graph, delta = graphs[key]
            wp.capture_launch(graph)
            solver.add_host_counts(delta)
        return solver.deferred_bad.numpy()

    def retry(reshape: bool, level: int, eager: bool, failing: list) -> np.ndarray:
        """Redo the frame from its start for ``failing`` only, at 2^level solver steps per substep.

        The other instances are held: restored afterwards to the state they reached, and in between
        pinned at the frame start with zero velocity and no body, so they neither move nor change
        the retried ones, and no instance's result depends on its batch mates' failures.
        """
        hold = np.ones(N, dtype=np.int32)
        hold[failing] = 0
        accepted.assign(state)
        state.assign(frame_backup)
        wp.copy(collider.points, body_backup)
        pinned = wp.clone(model.vertex_pinned)
        ids = collider.mesh_ids.numpy().copy()  # .numpy() is a view of the array on the CPU
        collider.mesh_ids.assign(np.where(hold != 0, np.uint64(0), ids))
        held.assign(hold)
        wp.launch(_hold_instances, dim=model.num_vertices, device=device,
                  inputs=[pinned, model.vertex_instance, held, model.vertex_pinned, state.velocities])
        bad = attempt(reshape, level, eager)
        collider.mesh_ids.assign(ids)
        wp.copy(model.vertex_pinned, pinned)
        wp.launch(_select_instances, dim=model.num_vertices, device=device,
                  inputs=[accepted.positions, accepted.velocities, model.vertex_instance, held,
                          state.positions, state.velocities])
        return bad

    failures: dict[int, SimulationFailure] = {}

    def freeze(instances, phase: str, k: int, message: str) -> None:
        # Back to the frame start, pinned there with no body: the instance stops; its slot fails.
        chosen = np.zeros(N, dtype=np.int32)
        chosen[list(instances)] = 1
        held.assign(chosen)
        wp.launch(_select_instances, dim=model.num_vertices, device=device,
                  inputs=[frame_backup.positions, frame_backup.velocities, model.vertex_instance, held,
                          state.positions, state.velocities])
        pinned = model.vertex_pinned.numpy()
        ids = collider.mesh_ids.numpy()
        vel = state.velocities.numpy()
        for i in instances:
            failures[i] = SimulationFailure(keys[i], message, phase, k)
            pinned[starts[i]:starts[i + 1]] = 1
            vel[starts[i]:starts[i + 1]] = 0.0
            ids[i] = 0
        model.vertex_pinned.assign(pinned)
        collider.mesh_ids.assign(ids)
        state.velocities.assign(vel)

    def run_frame(reshape: bool, phase: str, k: int, first: bool) -> None:
        """One frame for every live instance; failing instances are redone alone at finer steps.

        The guard's bits are read once per attempt. Instances that failed are redone from the frame
        start with every substep split in two, then four, ... (``max_retries`` levels) while the
        others are held (:func:`retry`); one still not finite after the last level is frozen and
        fails, one that is finite but still failing the guard is kept and counted unresolved.
        The first frame runs uncaptured (it loads every kernel and takes the first lagged contacts).
        """
        frame_backup.assign(state)
        wp.copy(body_backup, collider.points)
        eager = first or not use_graph
        bad = attempt(reshape, 0, eager)
        failing = [i for i in range(N) if bad[i] and i not in failures]
        level = 0
        while failing and level < max_level:
            level += 1
            solver.count_retries(failing)
            bad = retry(reshape, level, eager, failing)
            failing = [i for i in failing if bad[i]]
        if failing:
            diverged = [i for i in failing if bad[i] & 1]
            solver.count_unresolved([i for i in failing if not bad[i] & 1])
            if diverged:
                freeze(diverged, phase, k, f"the cloth step still produced non-finite positions after "
                                           f"{max_level} retries at up to {2 ** max_level} solver steps per substep")
        if level > 0:
            # Friction's lagged contacts at the frame's end for every instance (the retry took the
            # held instances' without their body).
            solver.take_contacts(state, collider)

    out_positions = [[] for _ in range(N)]
    out_stats = [[] for _ in range(N)]
    out_body = [[] for _ in range(N)]
    proto_positions = [[] for _ in range(N)]
    proto_stats = [[] for _ in range(N)]
    proto_phases = []
    total = len(schedule)
    current_betas = np.zeros((N, nb))
    t_start = time.perf_counter()
    for done, (phase, k) in enumerate(schedule):
        t0 = time.perf_counter()
        solver.reset_stats()
        # Output frame 0 of the animation is the protocol's end state: no step, only statistics.
        if not (phase == "animate" and k == 0) and len(failures) < N:
            q, tr, bt = body_targets(phase, k)
            quats_dev.assign(np.ascontiguousarray(q, dtype=np.float32))
            trans_dev.assign(np.ascontiguousarray(tr, dtype=np.float32))
            # Re-shape only while the betas change (ramp), never for a shapeless body model.
            reshape = body.num_betas > 0 and not np.all(bt == current_betas[None])
            if reshape:
                betas_dev.assign(np.ascontiguousarray(bt, dtype=np.float32))
            wp.synchronize_device(device)
            t_step = time.perf_counter()
            run_frame(reshape, phase, k, first=(done == 0))
            wp.synchronize_device(device)
            step_time = time.perf_counter() - t_step
            current_betas = np.array(bt[-1])
        else:
            step_time = 0.0
        rows = stats_probe.measure(state.positions, current_betas)
        st = solver.stats
        per = solver.instance_stats
        x = state.positions.numpy().astype(np.float32)
        wall = time.perf_counter() - t0
        body_now = wbody.vertices.numpy() if cfg.record_body and phase == "animate" else None
        for i in range(N):
            if i in failures:
                continue
            row = rows[i]
            row.update(depth_before_projection=float(per["max_penetration"][i]), retries=int(per["retries"][i]),
                       unresolved=int(per["unresolved"][i]), newton_iterations=st["newton_iterations"],
                       cg_iterations=st["cg_iterations"], step_time=step_time, wall_time=wall)
            xi = x[starts[i]:starts[i + 1]]
            if phase == "animate":
                if k < num_out[i]:
                    out_positions[i].append(xi)
                    out_stats[i].append(row)
                    if body_now is not None:
                        out_body[i].append(body_now[i].astype(np.float32))
            else:
                proto_positions[i].append(xi)
                proto_stats[i].append(row)
        if phase != "animate":
            proto_phases.append(phase)
        if progress is not None:
            progress(done + 1, total, phase)
    wall_total = time.perf_counter() - t_start

    body_faces = wbody.faces.numpy().reshape(-1, 3).astype(np.int32)
    results: list = []
    for i in range(N):
        if i in failures:
            results.append(failures[i])
            continue
        stats = stack_stats(out_stats[i])
        metadata = dict(
            key=keys[i], garment=garment.name, garment_vertices=int(nv), garment_triangles=int(len(garment.faces)),
            body=body.name, body_vertices=int(body.num_vertices), motion=clips[i].name, motion_fps=float(clips[i].fps),
            fps=fps, substeps=S, dt=h, frames=num_out[i], betas=[float(b) for b in target_betas[i]],
            material=asdict(materials[i]),
            config=dict(relax_frames=cfg.relax_frames, ramp_frames=cfg.ramp_frames, rest_frames=cfg.rest_frames,
                        self_intersection_probe=cfg.self_intersection_probe, query_distance=cfg.query_distance,
                        device=str(device), cuda_graph=use_graph),
            solver=json.loads(json.dumps(asdict(cfg.solver), default=float)),
            batch_size=N,
            initial_inside=int(initial[i]["inside_count"]),
            wall_time=wall_total,
            wall_time_per_frame=wall_total / total,
            max_depth_regular=float(stats["max_depth_regular"].max()),
            max_self_intersection_count=int(stats["self_intersection_count"].max()),
            retries=int(stats["retries"].sum() + sum(r["retries"] for r in proto_stats[i])),
        )
        results.append(SimulationResult(
            positions=np.stack(out_positions[i]),
            faces=np.asarray(garment.faces, dtype=np.int32),
            fps=fps, dt=h, stats=stats,
            protocol_positions=np.stack(proto_positions[i]) if proto_positions[i] else np.zeros((0, nv, 3), np.float32),
            protocol_phases=np.array(proto_phases, dtype=str),
            protocol_stats=(stack_stats(proto_stats[i]) if proto_stats[i]
                            else {key: np.zeros(0) for key in FRAME_STAT_KEYS}),
            body_vertices=np.stack(out_body[i]) if cfg.record_body else None,
            body_faces=body_faces,
            metadata=metadata,
        ))
    return results
