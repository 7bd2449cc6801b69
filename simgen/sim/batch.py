"""Setup of a batched simulation: the inputs resolved and checked, one cloth model instance per
slot, the solver, the posed body and its collider, and where each job's garment starts.

:func:`setup_batch` returns a :class:`BatchSetup`, what :class:`simgen.sim.frame_runner.FrameRunner`
steps, :class:`simgen.sim.recorder.JobRecorder` records and :class:`simgen.sim.pool.SimulationPool`
fills with jobs.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
import warp as wp

from simgen.errors import InputError
from simgen.materials import Material, get_material
from simgen.sim.collider import BodyCollider
from simgen.sim.config import SimulationConfig
from simgen.sim.frame_stats import FrameStats
from simgen.sim.model import ClothModel, ClothState
from simgen.sim.solver import ImplicitSolver

__all__ = ["SimulationJob", "BatchSetup", "setup_batch", "check_job", "resolve_clip", "resolve_inputs", "job_material",
           "frame_rate"]


@dataclass(frozen=True)
class SimulationJob:
    """One instance of :func:`simgen.sim.simulate_batch`.

    clip: :class:`MotionClip` or a library motion name; betas: (B',) shape coefficients (None:
    zeros); frames: output frames (None: the whole clip; more than it holds repeat its last pose);
    key: a label carried into the result's metadata and into failures (default: the job's index);
    material: preset name or :class:`Material` (None: the config's, with its overrides);
    substeps_factor: 1, 2, 4, ...: the job runs at that many times the config's substeps (its solver
    steps that much shorter; in a :class:`simgen.sim.SimulationPool` it takes that many pool frames
    per frame of its own), e.g. a retry of a job that failed at the config's.
    """

    clip: object
    betas: object = None
    frames: int | None = None
    key: str | None = None
    material: str | Material | None = None
    substeps_factor: int = 1


@dataclass
class BatchSetup:
    """The device side of a batched simulation of N slots, held for its whole run.

    config: the :class:`SimulationConfig`; garment, body: the resolved inputs; fps [1/s]: output
    frame rate of every job; materials: one per slot; model: the :class:`ClothModel` of N
    instances; state: its :class:`ClothState`; solver: the :class:`ImplicitSolver`; wbody: the
    posed :class:`simgen.body.warp_lbs.WarpBody` (N instances); collider: its
    :class:`BodyCollider`; stats: the :class:`FrameStats` probe; start_positions [m] (V, 3)
    float64: where every job's garment starts, the template placed on the template body at rest
    with no root translation (vertices found inside it projected out; a job adds its clip's
    first-frame translation); initial_inside: how many template vertices were found inside.
    """

    config: SimulationConfig
    garment: object
    body: object
    fps: float
    materials: list[Material]
    model: ClothModel
    state: ClothState
    solver: ImplicitSolver
    wbody: object
    collider: BodyCollider
    stats: FrameStats
    start_positions: np.ndarray
    initial_inside: int
    device: object

    @property
    def num_instances(self) -> int:
        return len(self.materials)

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


def check_job(job, i=0) -> None:
    """InputError unless ``job`` (the i-th) is a :class:`SimulationJob` with a valid frame count."""
    if not isinstance(job, SimulationJob):
        raise InputError(f"job {i} must be a SimulationJob, got {type(job).__name__}")
    f = job.frames
    if f is not None and (isinstance(f, bool) or not isinstance(f, (int, np.integer)) or f < 1):
        raise InputError(f"frames must be an integer >= 1, got {f!r}")
    k = job.substeps_factor
    if isinstance(k, bool) or not isinstance(k, (int, np.integer)) or k < 1 or k & (k - 1):
        raise InputError(f"substeps_factor must be a power of two >= 1 (1, 2, 4, ...), got {k!r}")


def resolve_clip(clip, cache: dict | None = None):
    """A :class:`MotionClip`, or a library motion name loaded (once per name with ``cache``)."""
    from simgen.motion.clip import MotionClip
    from simgen.motion.library import load_motion

    cache = {} if cache is None else cache
    return _resolve("clip", clip, lambda name: cache.setdefault(name, load_motion(name)), MotionClip)


def resolve_inputs(garment, body, config):
    """Check the config; load body and garment given by name. Returns (garment, body, config)."""
    from simgen import body as body_pkg
    from simgen.body.model import BodyModel
    from simgen.garment.garment import Garment
    from simgen.garment.library import load_garment

    config = config if config is not None else SimulationConfig()
    if not isinstance(config, SimulationConfig):
        raise InputError(f"config must be a SimulationConfig, got {type(config).__name__}")
    body = _resolve("body", body, body_pkg.load, BodyModel)
    garment = _resolve("garment", garment, lambda name: load_garment(name, body=body), Garment)
    return garment, body, config


def job_material(config: SimulationConfig, garment, job: SimulationJob) -> Material:
    """The material a job simulates: its own (with the config's overrides) or the config's."""
    if job.material is None:
        return config.resolve_material(garment)
    return replace(get_material(job.material), **config.material_overrides)


def frame_rate(config: SimulationConfig, clips) -> float:
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


def setup_batch(garment, body, materials: list[Material], fps: float, config: SimulationConfig) -> BatchSetup:
    """Build the device side of N = len(materials) slots: model, solver, body and collider, and
    where each job's garment starts (the template on the template body at rest; vertices found
    inside it are projected out, once for all jobs).

    garment, body: resolved (:func:`resolve_inputs`); fps [1/s]: output frame rate.
    """
    from simgen.body.warp_lbs import WarpBody

    cfg = config
    N = len(materials)
    device = wp.get_device(cfg.device)
    model = _build_model(garment, body, materials, device)
    solver = ImplicitSolver(model, cfg.solver)
    wbody = WarpBody(body, max_batch=N, device=device)
    # Template body at rest, no root translation; each job moves both by its clip's first translation.
    wbody.set_shape(np.zeros((1, body.num_betas)), num_instances=N)
    identity = np.zeros((N, 24, 4), dtype=np.float32)
    identity[..., 3] = 1.0                                                              # xyzw
    wbody.pose_from_quats(wp.array(identity, dtype=wp.quat, device=device),
                          wp.zeros(N, dtype=wp.vec3, device=device))
    collider = BodyCollider.from_warp_body(wbody, device=device)
    state = model.state()
    x0 = np.tile(np.asarray(garment.vertices, dtype=np.float32), (N, 1))
    state.positions.assign(x0)
    state.velocities.zero_()
    stats = FrameStats(model, collider, wbody, garment, body, contact=cfg.solver.contact)
    inside = stats.measure(state.positions, np.zeros((N, max(body.num_betas, 1))), [0])[0]["inside_count"]
    if inside:
        # The garment must never start inside the body: project what a bad template left inside.
        collider.project(model, state, offset=cfg.solver.projection_offset,
                         query_distance=cfg.solver.contact.query_distance,
                         pinch_distance=cfg.solver.contact.pinch_distance)
    start = state.positions.numpy()[:garment.num_vertices].astype(np.float64)
    return BatchSetup(config=cfg, garment=garment, body=body, fps=float(fps), materials=list(materials),
                      model=model, state=state, solver=solver, wbody=wbody, collider=collider, stats=stats,
                      start_positions=start, initial_inside=int(inside), device=device)
