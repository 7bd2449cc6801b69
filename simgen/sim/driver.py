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
solver takes one step (a retried frame splits it further, with the body moving linearly:
:mod:`simgen.sim.frame_runner`). The solver's projection (``SolverConfig.project``) pushes any vertex found inside
the body back onto it after every step, so output frames are free of penetration except where the
posed body intersects itself.

A batched simulation is a :class:`simgen.sim.pool.SimulationPool` of N slots (the dataset generator
keeps one running and feeds it jobs as slots free up; :func:`simulate_batch` gives it one slot per
job), made of four parts:

- :func:`simgen.sim.batch.setup_batch`: the cloth model of N instances, solver, posed body,
  collider, and where each job's garment starts (:class:`~simgen.sim.batch.BatchSetup`);
- :class:`simgen.sim.protocol.JobSchedule`: a job's frames in order and the body's targets at each
  substep;
- :class:`simgen.sim.frame_runner.FrameRunner`: one frame of substeps (CUDA graphs), the retry of
  failed instances at finer steps, the freezing of diverged ones, and the slots that start a job;
- :class:`simgen.sim.recorder.JobRecorder`: a job's per-frame statistics
  (:class:`simgen.sim.frame_stats.FrameStats`: penetration, body self-intersections, whether the
  garment is on the body) and positions, and its result.
"""

from __future__ import annotations

from dataclasses import replace

from simgen.errors import InputError
from simgen.sim.batch import SimulationJob, check_job, frame_rate, job_material, resolve_clip, resolve_inputs
from simgen.sim.config import SimulationConfig
from simgen.sim.frame_stats import FRAME_STAT_KEYS
from simgen.sim.pool import SimulationPool
from simgen.sim.protocol import PHASES
from simgen.sim.recorder import SimulationFailure, SimulationResult

__all__ = ["SimulationConfig", "SimulationResult", "SimulationJob", "SimulationFailure", "simulate",
           "simulate_batch", "PHASES", "FRAME_STAT_KEYS"]


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


def simulate_batch(garment, body, jobs, config: SimulationConfig | None = None, *,
                   progress=None) -> list:
    """Simulate N jobs of one garment on one body model as one batched system.

    Every :class:`SimulationJob` is its own instance (garment copy, material, body shape, motion) of
    one :class:`ClothModel` with N instances and one posed body mesh each; all step together
    through the start protocol and the animation (:func:`simulate` describes both): a
    :class:`simgen.sim.pool.SimulationPool` with one slot per job. A job that ends before the
    longest (a shorter clip) leaves its slot idle. All clips must share one frame rate (config.fps,
    or the clips' own when it is None).

    On CUDA each frame's substeps (body posing, refits, solver) replay as one captured CUDA graph
    (``config.cuda_graph``); the CPU runs the same sequence uncaptured. Instances that fail the
    solver's guard are redone alone at finer steps, and one still not finite after the last level
    is frozen and its slot returns a :class:`SimulationFailure`; the others go on
    (:mod:`simgen.sim.frame_runner`).

    progress: optional callable(done, total, phase) after each batch frame (protocol included).
    Returns one :class:`SimulationResult` or :class:`SimulationFailure` per job, in order.
    """
    garment, body, cfg = resolve_inputs(garment, body, config)
    jobs = list(jobs)
    if not jobs:
        raise InputError("simulate_batch needs at least one SimulationJob")
    cache: dict = {}
    for i, job in enumerate(jobs):
        check_job(job, i)
    clips = [resolve_clip(j.clip, cache) for j in jobs]
    pool = SimulationPool(garment, body, len(jobs), cfg, fps=frame_rate(cfg, clips),
                          materials=[job_material(cfg, garment, j) for j in jobs])
    for i, (job, clip) in enumerate(zip(jobs, clips)):
        pool.submit(replace(job, clip=clip), tag=i)
    pool.fill()
    total = pool.next_frames()
    results: list = [None] * len(jobs)
    for done in range(1, total + 1):
        phase = pool.current_phase()
        for i, res in pool.step():
            results[i] = res
        if progress is not None:
            progress(done, total, phase)
    return results
