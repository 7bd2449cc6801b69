"""A long-lived batched simulation of N slots that take jobs as they free up (continuous batching).

:class:`SimulationPool` holds one garment on one body model in N slots (one cloth instance and one
posed body each) and steps every busy slot one frame at a time. Each slot runs its own job from
its own first frame: the start protocol (relax, ramp, rest: :mod:`simgen.sim.driver`) and then its
clip, with the body targets of its own :class:`simgen.sim.protocol.JobSchedule`. When a job has
recorded its last frame the slot takes the next queued job at the next frame boundary, so the
batch stays full until the queue runs out; a slot with nothing to do is idle (pinned, no body:
:mod:`simgen.sim.frame_runner`). Instances never interact, so a job's result does not depend on
what its batch mates are doing (up to float summation order), only on its own inputs.

A job with ``substeps_factor`` k (a dataset's retry of a job that failed at the pool's substeps)
runs in a slot like any other, with its solver steps k times shorter
(:attr:`ClothModel.instance_step_divisor`): each pool frame advances it by 1/k of a frame, with
body targets at its own substeps' times, and it records a frame every k pool frames, so it never
needs a pool of its own.

A clip's output frame 0 is the rest phase's end state and takes no step: it is recorded with the
job's last protocol frame. The frames a pool steps therefore number, per job, the protocol frames
plus the output frames minus one (the cloth-frames of :func:`simgen.dataset.execute.job_cloth_frames`).

:func:`simgen.sim.simulate_batch` is a pool with one slot per job, all submitted at once.
"""

from __future__ import annotations

import time
from collections import deque
from dataclasses import dataclass

import numpy as np

from simgen.errors import InputError
from simgen.sim.batch import SimulationJob, check_job, job_material, resolve_clip, resolve_inputs, setup_batch
from simgen.sim.frame_runner import FrameRunner
from simgen.sim.protocol import JobSchedule
from simgen.sim.recorder import JobRecorder, measure_frame

__all__ = ["SimulationPool"]


@dataclass(eq=False)   # found in the queue by identity (fields hold arrays and clips)
class _Queued:
    tag: object
    job: SimulationJob
    clip: object
    material: object
    num_out: int
    betas: np.ndarray
    factor: int = 1          # the job's substeps_factor: pool frames per frame of its own


@dataclass(eq=False)
class _Running:
    tag: object
    schedule: JobSchedule
    recorder: JobRecorder
    factor: int = 1          # pool frames per schedule frame (the job's substeps_factor)
    cursor: int = 0          # index into schedule.frames of the next frame to step
    sub: int = 0             # pool frames of that frame already stepped (< factor)


class SimulationPool:
    """N slots of one garment on one body model; jobs queue and run as slots free up.

    garment, body: a :class:`simgen.garment.Garment` made on this body and a
      :class:`simgen.body.BodyModel` (or their names); slots: N >= 1; config:
      :class:`SimulationConfig` (None: defaults); fps [1/s]: the output frame rate of every job
      (``config.fps`` if set, else this; clips are sampled at k / fps, so a clip at another rate is
      refused only when config.fps is None); materials: one :class:`Material` per slot (None: the
      config's for all); a job runs in a slot of its material.

    :meth:`submit` queues jobs; :meth:`step` fills idle slots from the queue (first in, first out,
    among the jobs whose material an idle slot has), steps one frame and returns the jobs that ended.
    ``accept``: None, or a callable(tag, cloth_frames) -> bool asked before a queued job starts; a job
    it refuses leaves the queue and its tag goes to ``refused`` (e.g. a time budget). ``gate``: None,
    or a callable(tag, k, row) -> str | None asked as each job records animation frame k with its
    row of :data:`FRAME_STAT_KEYS`; a message ends the job there as a :class:`SimulationFailure`
    (e.g. a dataset's quality limits, so that a retry starts at once instead of after the clip).
    """

    def __init__(self, garment, body, slots: int, config=None, *, fps: float | None = None,
                 materials: list | None = None) -> None:
        garment, body, cfg = resolve_inputs(garment, body, config)
        if isinstance(slots, bool) or not isinstance(slots, (int, np.integer)) or slots < 1:
            raise InputError(f"a simulation pool needs slots >= 1, got {slots!r}")
        rate = cfg.fps if cfg.fps is not None else fps
        if rate is None or not float(rate) > 0:
            raise InputError(f"a simulation pool needs its frame rate: set SimulationConfig.fps or fps, got {rate!r}")
        if materials is None:
            materials = [cfg.resolve_material(garment)] * int(slots)
        if len(materials) != slots:
            raise InputError(f"{len(materials)} materials for {slots} slots")
        self.config, self.garment, self.body = cfg, garment, body
        self.setup = setup_batch(garment, body, list(materials), float(rate), cfg)
        self.runner = FrameRunner(self.setup)
        self._queue: deque[_Queued] = deque()
        self._running: dict[int, _Running] = {}
        self._clips: dict = {}
        self.accept = None
        self.gate = None
        self.refused: list = []
        self._recent: deque = deque(maxlen=32)   # [s] wall time of the last frames
        self.frames_run = 0          # frames stepped
        self.cloth_frames = 0        # job frames stepped (a job at k times the substeps: one per k pool frames)
        self.step_time = 0.0         # [s] the solver's stepping summed over frames
        self.last_frame: dict = {}   # the last step(): busy slots, wall and stepping [s], solver retries
        self.wall = 0.0              # [s] wall time of step() summed

    # -- queue --------------------------------------------------------------------------------------
    @property
    def num_slots(self) -> int:
        return self.setup.num_instances

    @property
    def queued(self) -> int:
        return len(self._queue)

    @property
    def queued_frames(self) -> int:
        """Pool frames the queued jobs will take (each job's frames times its substeps_factor)."""
        return sum(self._cloth_frames_of(e) for e in self._queue)

    @property
    def busy(self) -> int:
        """Slots running a job (or about to start one at the next frame)."""
        return len(self._running)

    def submit(self, job: SimulationJob, tag=None) -> None:
        """Queue ``job``; ``tag`` comes back with its result (default: the job)."""
        check_job(job)
        cfg, s = self.config, self.setup
        clip = resolve_clip(job.clip, self._clips)
        if cfg.fps is None and abs(float(clip.fps) - s.fps) > 1e-9:
            raise InputError(f"clip {clip.name!r} runs at {clip.fps:g} fps but the pool's jobs at {s.fps:g}; the clips "
                             f"of one batch need the same frame rate (or set SimulationConfig.fps)")
        material = job_material(cfg, self.garment, job)
        if not any(m == material for m in s.materials):
            raise InputError(f"job {job.key!r} asks for material {material.name!r}, which no slot of the pool has")
        num_out = int(np.floor(clip.duration * s.fps + 1e-9)) + 1 if job.frames is None else int(job.frames)
        betas = (np.zeros(self.body.num_betas) if job.betas is None
                 else self.body.check_betas(job.betas).reshape(-1))
        self._queue.append(_Queued(job if tag is None else tag, job, clip, material, num_out, betas,
                                   int(job.substeps_factor)))

    def recent_frame_time(self) -> float | None:
        """[s] The median wall time of the last frames (after the first two, which load kernels and
        capture graphs; until then the mean of those), or None before any frame."""
        if self._recent:
            return float(np.median(self._recent))
        return self.wall / self.frames_run if self.frames_run else None

    def current_phase(self) -> str | None:
        """The phase of the coming frame of the first busy slot (None when none is busy)."""
        run = next((self._running[k] for k in sorted(self._running)), None)
        return None if run is None else run.schedule.frames[run.cursor][0]

    def frames_left(self) -> list:
        """[(tag, pool frames its job still has to step)] of the running jobs, in slot order (the
        clip's frame 0 takes no step; a job at k times the substeps takes k pool frames a frame)."""
        return [(r.tag, (len(r.schedule.frames) - r.cursor - (r.cursor < r.schedule.protocol_frames)) * r.factor - r.sub)
                for _, r in sorted(self._running.items())]

    def next_frames(self) -> int:
        """Pool frames the longest running job still has to step (0 when nothing runs)."""
        return max((n for _, n in self.frames_left()), default=0)

    # -- stepping -----------------------------------------------------------------------------------
    def fill(self) -> None:
        """Start queued jobs in the idle slots (those ``accept`` lets start)."""
        for slot in range(self.num_slots):
            if slot in self._running or not self._queue:
                continue
            material = self.setup.materials[slot]
            entry = next((q for q in self._queue if q.material == material), None)
            if entry is None:
                continue
            self._queue.remove(entry)
            if self.accept is not None and not self.accept(entry.tag, self._cloth_frames_of(entry)):
                self.refused.append(entry.tag)
                continue
            self._start(slot, entry)

    def drop_queue(self) -> list:
        """Remove every queued job; their tags."""
        tags = [q.tag for q in self._queue]
        self._queue.clear()
        return tags

    def abandon(self) -> list:
        """Stop every running job where it is, without a result (its slot goes idle); their tags."""
        tags = [self._running[slot].tag for slot in sorted(self._running)]
        self.runner.release(list(self._running))
        self._running.clear()
        return tags

    def step(self) -> list:
        """Fill idle slots (:meth:`fill`), step one frame of every busy slot and return the jobs
        that ended with it: [(tag, SimulationResult or SimulationFailure)] in slot order."""
        self.fill()
        if not self._running:
            return []
        t_frame = time.perf_counter()
        s, runner = self.setup, self.runner
        where = self._frame_targets()
        s.solver.reset_stats()
        runner.run(*self._targets, where)
        rows, x, body = measure_frame(s, runner.betas_now, runner.step_time, t_frame, list(self._running))
        failed = runner.take_failures()
        done, starts, framed = [], np.asarray(s.model.vertex_start), 0
        for slot in sorted(self._running):
            run = self._running[slot]
            if slot in failed:
                done.append((slot, run.tag, run.recorder.failure(*failed[slot])))
                framed += 1
                continue
            run.sub += 1
            if run.sub < run.factor:      # part of the job's frame: its statistics add up, nothing recorded
                run.recorder.hold(rows[slot])
                continue
            run.sub = 0
            framed += 1
            xi = x[starts[slot]:starts[slot + 1]]
            bi = None if body is None else body[slot]
            phase, k = where[slot]
            run.recorder.record(phase, k, rows[slot], xi, bi)
            run.cursor += 1
            if run.cursor == run.schedule.protocol_frames:           # the clip's frame 0: no step
                run.recorder.record_start(rows[slot], xi, bi)
                run.cursor += 1
                phase, k = "animate", 0
            verdict = None if self.gate is None or phase != "animate" else self.gate(run.tag, k, rows[slot])
            if verdict is not None:        # the job fails here; the rest of its clip is not stepped
                done.append((slot, run.tag, run.recorder.failure(phase, k, verdict)))
                continue
            if run.cursor >= len(run.schedule.frames):
                done.append((slot, run.tag, run.recorder.result()))
        wall = time.perf_counter() - t_frame
        for run in self._running.values():
            run.recorder.share += wall / len(self._running)
        self.last_frame = {"busy": len(self._running), "wall": wall, "step": runner.step_time,
                           "retries": s.solver.host_counts()["retries"]}
        self.frames_run += 1
        if self.frames_run > 2:      # the first frames load kernels and capture CUDA graphs
            self._recent.append(wall)
        self.cloth_frames += framed
        self.step_time += runner.step_time
        self.wall += wall
        ended = [slot for slot, _, _ in done]
        runner.release([slot for slot in ended if slot not in failed])
        for slot in ended:
            del self._running[slot]
        return [(tag, res) for _, tag, res in done]

    def _cloth_frames_of(self, entry: _Queued) -> int:
        """Pool frames ``entry`` will take (its frames times its substeps_factor)."""
        c = self.config
        return (c.relax_frames + c.ramp_frames + c.rest_frames + entry.num_out - 1) * entry.factor

    def _start(self, slot: int, entry: _Queued) -> None:
        s, c = self.setup, self.config
        schedule = JobSchedule(entry.clip, self._padded(entry.betas), s.fps, c.substeps * entry.factor,
                               relax_frames=c.relax_frames, ramp_frames=c.ramp_frames, rest_frames=c.rest_frames,
                               animate_frames=entry.num_out)
        key = str(entry.job.key) if entry.job.key is not None else str(entry.tag)
        recorder = JobRecorder(s, key, entry.clip, entry.num_out, entry.betas, entry.material, entry.factor)
        quats, trans = schedule.start_pose()
        self.runner.place(slot, quats, trans, (s.start_positions + trans[None]).astype(np.float32), entry.factor)
        self._running[slot] = _Running(entry.tag, schedule, recorder, entry.factor)

    def _padded(self, betas: np.ndarray) -> np.ndarray:
        b = np.zeros(max(self.body.num_betas, 1))
        b[:len(betas)] = betas
        return b

    def _frame_targets(self) -> list:
        """Set ``_targets`` (quats (S, N, 24, 4), trans (S, N, 3), betas (S, N, nb)) for the coming frame;
        returns each slot's (phase, k) (None for idle slots)."""
        S, N = self.setup.substeps, self.num_slots
        q_now, tr_now = self.runner.pose_now
        quats = np.broadcast_to(q_now[None], (S, N, 24, 4)).copy()
        trans = np.broadcast_to(tr_now[None], (S, N, 3)).copy()
        betas = np.broadcast_to(self.runner.betas_now[None], (S,) + self.runner.betas_now.shape).copy()
        where: list = [None] * N
        for slot, run in self._running.items():
            phase, k = run.schedule.frames[run.cursor]
            where[slot] = (phase, k)
            rows = slice(run.sub * S, (run.sub + 1) * S)   # this pool frame's part of the job's frame
            q, tr, b = run.schedule.targets(phase, k)
            quats[:, slot], trans[:, slot], betas[:, slot] = q[rows], tr[rows], b[rows]
        self._targets = (quats, trans, betas)
        return where
