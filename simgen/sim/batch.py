"""Setup of a batched simulation: the inputs resolved and checked, one cloth model instance per job,
the solver, the posed body and its collider, and the garment placed on the template body.

:func:`setup_batch` returns a :class:`BatchSetup`, what :class:`simgen.sim.frame_runner.FrameRunner`
steps and :class:`simgen.sim.recorder.Recorder` records; :func:`simgen.sim.simulate_batch` composes
them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
import warp as wp

from simgen.errors import InputError
from simgen.materials import Material, get_material
from simgen.sim.collider import BodyCollider
from simgen.sim.config import SimulationConfig
from simgen.sim.frame_stats import FrameStats
from simgen.sim.model import ClothModel, ClothState
from simgen.sim.protocol import ProtocolSchedule
from simgen.sim.solver import ImplicitSolver

__all__ = ["SimulationJob", "BatchSetup", "setup_batch"]


@dataclass(frozen=True)
class SimulationJob:
    """One instance of :func:`simgen.sim.simulate_batch`.

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
class BatchSetup:
    """Everything a batched simulation of N jobs holds for its whole run.

    config: the :class:`SimulationConfig`; garment, body: the resolved inputs; clips, keys: one per
    job; fps [1/s]; num_out: output frames per job; betas (N, nb): target shapes (zero-padded to
    the body's nb >= 1 slots; target_betas keeps each job's own length); materials: one per job;
    model: the :class:`ClothModel` of N instances; state: its :class:`ClothState`, the garment
    placed on the template body; solver: the :class:`ImplicitSolver`; wbody: the posed
    :class:`simgen.body.warp_lbs.WarpBody` (N instances); collider: its :class:`BodyCollider`;
    stats: the :class:`FrameStats` probe; initial: its rows at the start (template vertices found
    inside the template body are projected out); schedule: the :class:`ProtocolSchedule`.
    """

    config: SimulationConfig
    garment: object
    body: object
    clips: list
    keys: list[str]
    fps: float
    num_out: list[int]
    target_betas: list[np.ndarray]
    betas: np.ndarray
    materials: list[Material]
    model: ClothModel
    state: ClothState
    solver: ImplicitSolver
    wbody: object
    collider: BodyCollider
    stats: FrameStats
    initial: list[dict]
    schedule: ProtocolSchedule
    device: object

    @property
    def num_instances(self) -> int:
        return len(self.keys)

    @property
    def substeps(self) -> int:
        return self.config.substeps

    @property
    def use_graph(self) -> bool:
        """Whether frames replay as captured CUDA graphs (``config.cuda_graph`` on a CUDA device)."""
        return bool(self.config.cuda_graph) and self.device.is_cuda

    @property
    def dt(self) -> float:
        """The solver substep [s]: the frame time 1 / fps over ``substeps``."""
        return (1.0 / self.fps) / self.config.substeps


def _resolve(kind: str, value, loader, cls):
    if isinstance(value, str):
        return loader(value)
    if not isinstance(value, cls):
        raise InputError(f"{kind} must be a {cls.__name__} or a {kind} name, got {type(value).__name__}")
    return value


def _resolve_inputs(garment, body, jobs, config):
    """Check the jobs and the config; load body, garment and clips given by name (each clip name once)."""
    from simgen import body as body_pkg
    from simgen.body.model import BodyModel
    from simgen.garment.garment import Garment
    from simgen.garment.library import load_garment
    from simgen.motion.clip import MotionClip
    from simgen.motion.library import load_motion

    if not isinstance(config, SimulationConfig):
        raise InputError(f"config must be a SimulationConfig, got {type(config).__name__}")
    jobs = list(jobs)
    if not jobs:
        raise InputError("simulate_batch needs at least one SimulationJob")
    for i, job in enumerate(jobs):
        if not isinstance(job, SimulationJob):
            raise InputError(f"job {i} must be a SimulationJob, got {type(job).__name__}")
        f = job.frames
        if f is not None and (isinstance(f, bool) or not isinstance(f, (int, np.integer)) or f < 1):
            raise InputError(f"frames must be an integer >= 1, got {f!r}")
    body = _resolve("body", body, body_pkg.load, BodyModel)
    garment = _resolve("garment", garment, lambda name: load_garment(name, body=body), Garment)
    by_name: dict = {}
    clips = [_resolve("clip", j.clip, lambda name: by_name.setdefault(name, load_motion(name)), MotionClip)
             for j in jobs]
    return garment, body, jobs, clips


def _frame_rate(config: SimulationConfig, clips) -> float:
    rates = sorted({float(c.fps) for c in clips})
    if config.fps is None and len(rates) > 1:
        raise InputError(f"the clips of one batch have different frame rates ({rates}); set SimulationConfig.fps")
    return float(config.fps) if config.fps is not None else rates[0]


def _build_model(garment, body, materials, device) -> ClothModel:
    """One model instance per job; jobs with equal materials reuse one built instance."""
    built: list = []
    for mat in materials:
        if not any(m == mat for m, _ in built):
            built.append((mat, ClothModel.from_garment(garment, mat, body=body, device=device)))
    parts = [next(mdl for m, mdl in built if m == mat) for mat in materials]
    return parts[0] if len(parts) == 1 else ClothModel.concatenate(parts)


def setup_batch(garment, body, jobs, config: SimulationConfig | None = None) -> BatchSetup:
    """Resolve and check the inputs, build the batch's model, solver, body and collider, and place
    each garment copy on the template body at rest at its clip's first-frame translation.

    garment, body, jobs, config: as :func:`simgen.sim.simulate_batch`. Raises InputError for bad
    input before anything is allocated on the device.
    """
    from simgen.body.warp_lbs import WarpBody

    cfg = config if config is not None else SimulationConfig()
    garment, body, jobs, clips = _resolve_inputs(garment, body, jobs, cfg)
    fps = _frame_rate(cfg, clips)
    num_out = [int(math.floor(c.duration * fps + 1e-9)) + 1 if j.frames is None else int(j.frames)
               for j, c in zip(jobs, clips)]
    target_betas = [np.zeros(body.num_betas) if j.betas is None else body.check_betas(j.betas).reshape(-1)
                    for j in jobs]
    N, nb = len(jobs), max(body.num_betas, 1)
    betas = np.zeros((N, nb))
    for i, b in enumerate(target_betas):
        betas[i, :len(b)] = b
    materials = [cfg.resolve_material(garment) if j.material is None
                 else replace(get_material(j.material), **cfg.material_overrides) for j in jobs]
    schedule = ProtocolSchedule(clips, betas, fps, cfg.substeps, relax_frames=cfg.relax_frames,
                                ramp_frames=cfg.ramp_frames, rest_frames=cfg.rest_frames,
                                animate_frames=max(num_out))
    device = wp.get_device(cfg.device)
    model = _build_model(garment, body, materials, device)
    solver = ImplicitSolver(model, cfg.solver)
    wbody = WarpBody(body, max_batch=N, device=device)
    # Template body at rest, translated to each clip's start; each garment rigidly with it.
    wbody.set_shape(np.zeros((1, body.num_betas)), num_instances=N)
    quats, trans = schedule.start_pose()
    wbody.pose_from_quats(wp.array(np.ascontiguousarray(quats), dtype=wp.quat, device=device),
                          wp.array(trans.astype(np.float32), dtype=wp.vec3, device=device))
    collider = BodyCollider.from_warp_body(wbody, device=device)
    state = model.state()
    x0 = (np.asarray(garment.vertices, dtype=np.float64)[None] + schedule.trans0[:, None]).astype(np.float32)
    state.positions.assign(x0.reshape(-1, 3))
    state.velocities.zero_()
    stats = FrameStats(model, collider, wbody, garment, body, contact=cfg.solver.contact)
    initial = stats.measure(state.positions, np.zeros((N, nb)))
    if any(r["inside_count"] for r in initial):
        # The garment must never start inside the body: project what a bad template left inside.
        collider.project(model, state, offset=cfg.solver.projection_offset,
                         query_distance=cfg.solver.contact.query_distance,
                         pinch_distance=cfg.solver.contact.pinch_distance)
    return BatchSetup(config=cfg, garment=garment, body=body, clips=clips,
                      keys=[str(j.key) if j.key is not None else str(i) for i, j in enumerate(jobs)],
                      fps=fps, num_out=num_out, target_betas=target_betas, betas=betas, materials=materials,
                      model=model, state=state, solver=solver, wbody=wbody, collider=collider, stats=stats,
                      initial=initial, schedule=schedule, device=device)
