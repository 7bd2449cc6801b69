"""Jobs, the tasks that run them, and the function that simulates a task's jobs and writes their nodes.

The plan of a store is a list of :class:`Job`: one ``template`` job (the garment relaxed on the
template body: betas 0, a one-frame rest-pose clip), one ``fit`` job per shape (same clip, betas
of the shape: relax, ramp the shape from 0, rest -> S_c(beta, 0)) and one ``sequence`` job per
(motion, shape) (relax, ramp shape and pose to the clip's first frame, rest, animate). Every job
runs simulate()'s start protocol from the garment template, so the relaxation of the thesis
("relax once, start every simulation from it") is re-run inside each job: it is deterministic
and the same for all jobs (the body is the template body at rest throughout), and simulate()
takes no initial state.

:func:`run_pool_task` runs in the driver (local execution) or in a Ray task: it keeps one
:class:`simgen.sim.SimulationPool` (:func:`pool_slots`) full with the task's jobs (continuous
batching: a slot whose job ended takes the next one at the next frame, each job with its own start
protocol; on Ray the pools of a round share their jobs, :class:`JobFeed`) and hands each job that
ends to a :class:`NodeWriter` (ground truth, statistics, Zarr,
commit), in background threads behind the simulation with ``execution.overlap_writes``. A job
that diverges fails while the others are written, and runs again with the substep halved (attempt
k runs substeps * 2^(k-1)) until ``execution.max_attempts``: in the same pool (the job's
``substeps_factor`` there) while the pool, by the work waiting for its slots and the work in
flight, will step for longer than the retry takes (:func:`pool_frames_left`), and its failed
attempt's outcome then says ``retry: "pool"``; else in
a small pool that the driver starts on the first free worker (a retry left to step on alone in a
draining pool pays for the idle slots around it: BENCHMARKS.md). A sequence with a
strain or depth outlier (a triangle or a vertex past the check's limits on some frame) is such a
failure too while attempts are left: the pool stops the attempt at that frame (:func:`_outlier`),
so its retry starts at once. The template is not retried in the pool (the fits
need it written first: the driver runs its retry alone, :mod:`simgen.dataset.generate`).
"""

from __future__ import annotations

import functools
import time
from collections import deque
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, replace

import numpy as np

from simgen._warp_log import quiet_warp
from simgen.dataset.storage import Location, StoreWriteError
from simgen.errors import InputError

__all__ = ["Job", "BatchTask", "JobFeed", "NodeWriter", "run_pool_task", "pool_slots", "rest_clip", "job_cloth_frames"]


@dataclass
class Job:
    """One simulation of the plan.

    kind: "template" | "fit" | "sequence"; id: node id (shape id for fits, "<motion>__<shape>" for
    sequences, "template"); clip: the MotionClip (resampled and trimmed); betas (B,) float64;
    shape_id, motion, split: what the node's attrs record; attempt: 1 for the first try.
    """

    kind: str
    id: str
    clip: object
    betas: np.ndarray
    shape_id: str | None = None
    motion: str | None = None
    split: str | None = None
    motion_source: str | None = None
    attempt: int = 1

    @property
    def key(self) -> str:
        return f"{self.kind}:{self.id}"

    @property
    def frames(self) -> int:
        return int(self.clip.num_frames)


@dataclass
class BatchTask:
    """What :func:`run_pool_task` needs, picklable for Ray: store location, spec, garment name, jobs
    (all of one attempt), attempt, the device (None: the spec's) and the body's hash; with a
    ``feed`` (:class:`JobFeed` or a proxy of one), ``jobs`` is the task's share, which sizes its pool,
    and the jobs it runs come from the feed under ``name``."""

    location: str
    spec: object
    garment: str
    jobs: list
    attempt: int = 1
    device: str | None = None
    body_hash: str | None = None
    feed: object = None      # a JobFeed shared with the other tasks of its round (None: its own jobs)
    name: str = "task"       # its name in the feed

    @property
    def substeps_factor(self) -> int:
        return 2 ** (self.attempt - 1)


def rest_clip(fps: float, name: str = "rest"):
    """A one-frame clip in the rest pose (zero rotations, zero translation)."""
    from simgen.motion.clip import MotionClip

    return MotionClip(name, fps, np.zeros((1, 24, 3)), np.zeros((1, 3)), {"source": "simgen.dataset rest pose"})


def job_cloth_frames(spec, jobs) -> int:
    """Cloth-frames the jobs simulate: (protocol + clip frames) per job; frame 0 of a clip takes no step."""
    return sum(spec.protocol_frames() + j.frames - 1 for j in jobs)


class JobFeed:
    """The jobs of the pool tasks of one round, handed out as their pools' slots free up: a task
    takes its own share first, then the longest sequence left of any task (work stealing, longest
    processing time first), so that the jobs started last, as the feed runs dry, are the round's
    shortest on every pool, which then end close together however fast each one's GPU turns out
    to be. A task that starts again (Ray re-runs it after its worker died) first gets back the
    jobs its earlier run took; those come out marked, since their nodes may be committed.

    parts: {task name: [Job, ...]}, each share in the order it is to run (longest first);
    marked: every job comes out marked (a task's own jobs, which a re-run of it may have committed).
    """

    def __init__(self, parts: dict, marked: bool = False) -> None:
        self.queues = {name: deque(jobs) for name, jobs in parts.items()}
        self.taken: dict = {name: [] for name in parts}
        self.started: set = set()
        self.marked = {j.key for jobs in parts.values() for j in jobs} if marked else set()

    def start(self, name: str) -> None:
        """Task ``name`` starts (again: what its earlier run took leads its share, marked)."""
        if name in self.started:
            self.marked |= {j.key for j in self.taken[name]}
            self.queues[name].extendleft(reversed(self.taken[name]))
            self.taken[name] = []
        self.started.add(name)

    def take(self, name: str, n: int) -> list:
        """Up to ``n`` (job, marked) for task ``name`` ([] when none is left anywhere)."""
        out = []
        while len(out) < n:
            own = self.queues[name]
            if own:
                out.append(own.popleft())
                continue
            stolen = self._longest_sequence()
            if stolen is None:
                break
            out.append(stolen)
        self.taken[name] += out
        marks = [j.key in self.marked for j in out]
        self.marked -= {j.key for j in out}
        return list(zip(out, marks))

    def _longest_sequence(self):
        """Take the longest sequence job left of any task (None if none is left): never a template
        or fit job, which the task that has them runs before its sequences (the fits need the
        template written)."""
        best = None
        for q in self.queues.values():
            for i, j in enumerate(q):
                if j.kind == "sequence" and (best is None or j.frames > best[2].frames):
                    best = (q, i, j)
        if best is None:
            return None
        del best[0][best[1]]
        return best[2]

    def left(self) -> int:
        """Jobs not taken yet, of all tasks."""
        return sum(len(q) for q in self.queues.values())

    def share_left(self, protocol_frames: int) -> float:
        """Cloth-frames of the jobs not taken yet over the round's tasks: what one pool can still
        expect from the feed (protocol_frames: each job's start protocol)."""
        frames = sum(protocol_frames + j.frames - 1 for q in self.queues.values() for j in q)
        return frames / max(len(self.queues), 1)

    def rest(self, name: str) -> list:
        """Take what is left of task ``name``'s own share (a task that stops early hands it back;
        should its run die before the driver hears of them, a start again gets them back)."""
        out = list(self.queues[name])
        self.queues[name].clear()
        self.taken[name] += out
        return out


#: Most slots a pool takes on a GPU; a CPU pool's slots without execution.batch_size.
MAX_GPU_SLOTS, CPU_SLOTS = 128, 4
#: [bytes] GPU memory one slot of a pool takes per garment vertex: the T-shirt's slot (4,424
#: vertices, with its body, collider and statistics) took 26 MB in pools of 85-128 slots on an H100
#: (BENCHMARKS.md), about 6,000 bytes per vertex; a third more is kept for other garments' contacts.
SLOT_BYTES_PER_GARMENT_VERTEX = 8_000
#: Share of the device's free memory a pool may fill.
SLOT_MEMORY_SHARE = 0.7


def pool_slots(spec, device: str, garment) -> int:
    """The slots of a generation pool: ``execution.batch_size``, or with 0 as many as
    ``SLOT_MEMORY_SHARE`` of the GPU's free memory holds (at most ``MAX_GPU_SLOTS``; ``CPU_SLOTS`` on
    the CPU)."""
    if spec.batch_size > 0:
        return spec.batch_size
    if not str(device).startswith("cuda"):
        return CPU_SLOTS
    import gc

    import warp as wp

    gc.collect()   # a pool that just ended may still hold device memory until collected

    free = wp.get_device(device).free_memory
    per = SLOT_BYTES_PER_GARMENT_VERTEX * garment.num_vertices
    return int(max(1, min(MAX_GPU_SLOTS, SLOT_MEMORY_SHARE * free // per)))


@functools.lru_cache(maxsize=4)
def _load_body(source: str):
    from simgen import body as body_pkg

    return body_pkg.load(source)


@functools.lru_cache(maxsize=8)
def _load_garment(name: str, body_source: str):
    from simgen.garment.library import load_garment

    return load_garment(name, body=_load_body(body_source))


def _frame_stats(result, faces, rest_inverse) -> tuple[dict, dict]:
    """Per-frame stats arrays (T,) (the solver's + strain) and the node's summary."""
    from simgen.dataset.quality import strain_summary

    per_frame = {k: np.asarray(v) for k, v in result.stats.items()}
    mean, mx = strain_summary(result.positions, faces, rest_inverse)
    per_frame["strain_mean"] = mean
    per_frame["strain_max"] = mx
    proto = result.protocol_stats or {}
    retries = int(np.sum(per_frame.get("retries", 0))) + int(np.sum(proto.get("retries", 0)))
    summary = {
        "max_penetration": float(np.max(per_frame["max_depth_regular"])) if "max_depth_regular" in per_frame else None,
        "max_depth": float(np.max(per_frame["max_depth"])) if "max_depth" in per_frame else None,
        "max_self_intersection_count": int(np.max(per_frame.get("self_intersection_count", 0))),
        "strain_mean": float(np.mean(mean)),
        "strain_max": float(np.max(mx)),
        "solver_retries": retries,
        "unresolved": int(np.sum(per_frame.get("unresolved", 0))) + int(np.sum(proto.get("unresolved", 0))),
        "initial_inside": int(result.metadata.get("initial_inside", 0)),
        "min_body_share": float(np.min(per_frame["body_share"])),
        "max_support_drop": float(np.max(per_frame["support_drop"])),
        "min_height": float(np.min(per_frame["min_height"])),
        "crossing_frames": int(np.sum(per_frame["crossing_edges"] > 0)),
        "max_crossing_edges": int(np.max(per_frame["crossing_edges"])),
    }
    return per_frame, summary


def _outlier(spec, job: Job, k: int, row: dict) -> str | None:
    """Why an attempt of ``job`` is to be simulated again at its clip's frame ``k``, or None (the
    pool's gate, :attr:`simgen.sim.SimulationPool.gate`, asks as each frame is recorded).

    A sequence with a frame that fails ``simgen dataset check``'s rules while attempts are left: a
    triangle away from body self-intersections stretched past the strain limit
    (``execution.retry_strain_outliers``; row ``strain_max_regular``, measured on the device), or
    a regular cloth vertex deeper inside the body than the depth limit
    (``execution.retry_depth_outliers``; ``max_depth_regular``). Such spikes come from a vertex the
    step left deep inside a fast limb, and a smaller substep makes that intrusion smaller; the
    attempt stops at that frame, so that its retry starts at once instead of after the rest of its
    clip. Outliers at body self-intersections, which the check counts apart and a smaller substep
    cannot undo, are not retried. The last attempt is written whatever its frames (the check
    reports them).
    """
    from simgen.dataset.quality import DEFAULT_MAX_DEPTH, DEFAULT_MAX_STRAIN

    if job.kind != "sequence" or job.attempt >= spec.max_attempts:
        return None
    strain, depth = float(row["strain_max_regular"]), float(row["max_depth_regular"])
    if spec.retry_strain_outliers and strain > DEFAULT_MAX_STRAIN:
        return (f"strain outlier: a triangle stretched {100 * strain:.0f}% at frame {k} (the check's limit is "
                f"{100 * DEFAULT_MAX_STRAIN:g}%)")
    if spec.retry_depth_outliers and depth > DEFAULT_MAX_DEPTH:
        return (f"depth outlier: a cloth vertex {1e3 * depth:.2f} mm inside the body at frame {k} (the check's "
                f"limit is {1e3 * DEFAULT_MAX_DEPTH:g} mm)")
    return None


def _rest_frames(result) -> np.ndarray:
    phases = np.asarray(result.protocol_phases)
    return np.asarray(result.protocol_positions)[phases == "rest"].astype(np.float32)


def _outcome_base(job: Job) -> dict:
    return {"kind": job.kind, "id": job.id, "attempt": job.attempt, "frames": job.frames, "motion": job.motion,
            "shape_id": job.shape_id, "split": job.split}


class NodeWriter:
    """Writes simulated jobs into a store as committed nodes: ground truth, statistics, Zarr.

    Host work only (numpy, Zarr, the store), so it may run in threads other than the simulation's:
    sequences share no state and may be written at once; the template and the fits one at a time,
    in the order they ended (a fit needs the template written before it).
    spec, config: the store's spec and the attempt's :class:`SimulationConfig`; garment, body: host
    objects; location: the store's :class:`Location`; slots: the pool's size (recorded).
    """

    def __init__(self, spec, config, garment, body, location: Location, slots: int) -> None:
        from simgen.dataset.quality import triangle_rest_inverse

        self.spec, self.config, self.garment, self.body, self.loc = spec, config, garment, body, location
        self.slots = int(slots)
        self.rest_inv = triangle_rest_inverse(garment.vertices, garment.faces)
        self.smoothing = spec.smoothing_params()
        self.faces = np.asarray(garment.faces)
        self.template_smoothed = None

    def write(self, job: Job, res) -> dict:
        """The outcome of one job (ok with its checksum, or failed / waiting with a message); its node
        is committed when ok. Raises :class:`StoreWriteError` when the store cannot be written."""
        from simgen.sim import SimulationFailure

        msg = None
        if isinstance(res, SimulationFailure):
            msg = f"{res.message} (phase {res.phase}, frame {res.frame})"
        elif res.positions.shape[0] != job.frames:
            msg = f"the solver returned {res.positions.shape[0]} frames for a clip of {job.frames}"
        elif not np.all(np.isfinite(res.positions)):
            msg = "non-finite positions (NaN or inf) in the result"
        if msg is not None:
            return {**_outcome_base(job), "ok": False, "message": msg}
        per_frame, summary = _frame_stats(res, self.faces, self.rest_inv)
        summary.update(wall_time=float(res.metadata.get("wall_share", res.metadata["wall_time"])),
                       batch_size=self.slots, attempts=job.attempt, substeps=int(res.metadata["substeps"]),
                       device=str(self.config.device))
        if job.kind == "template":
            arrays, attrs = self._template(res, summary)
        elif job.kind == "fit":
            if self.template_smoothed is None:
                self.template_smoothed = _stored_template_smoothed(self.loc)
            if self.template_smoothed is None:
                return {**_outcome_base(job), "ok": False, "waiting": True,
                        "message": "the template relaxation is not in the store yet"}
            arrays, attrs = self._fit(job, res, summary)
        else:
            arrays, attrs = self._sequence(job, res, per_frame, summary)
        chunks = {"garment_vertices": (self.spec.chunk_frames,) + res.positions.shape[1:],
                  "rest_garment_vertices": (self.spec.chunk_frames,) + res.positions.shape[1:]}
        commit = self.loc.write_node(_node_rel(job), arrays, attrs, chunks=chunks)
        return {**_outcome_base(job), "ok": True, "checksum": commit["checksum"]}

    def _template(self, res, summary) -> tuple[dict, dict]:
        from simgen.dataset.groundtruth import smooth_garment

        garment, faces = self.garment, self.faces
        relaxed = res.positions[0].astype(np.float64)
        # Rounded to the stored float32 so fits of this run and of later ones subtract the same T_c.
        smoothed = smooth_garment(relaxed, faces, self.smoothing).astype(np.float32).astype(np.float64)
        self.template_smoothed = smoothed
        arrays = {"vertices": relaxed.astype(np.float32), "smoothed": smoothed.astype(np.float32),
                  "faces": faces.astype(np.int32), "skin_weights": np.asarray(garment.skin_weights, dtype=np.float32),
                  "garment_template": np.asarray(garment.vertices, dtype=np.float32)}
        attrs = {"smoothing": self.smoothing.to_dict(), "stats": summary, "garment": garment.name,
                 "protocol_frames": self.spec.protocol_frames()}
        return arrays, attrs

    def _fit(self, job, res, summary) -> tuple[dict, dict]:
        from simgen.dataset.groundtruth import fit_displacement

        fit_v = res.positions[0].astype(np.float64)
        arrays = {"betas": _full_betas(job.betas, self.body).astype(np.float32), "vertices": fit_v.astype(np.float32),
                  "fit_displacement": fit_displacement(fit_v, self.template_smoothed, self.faces, self.smoothing
                                                       ).astype(np.float32)}
        if self.spec.store_rest_frames:
            arrays["rest_vertices"] = _rest_frames(res)
        attrs = {"shape_id": job.shape_id, "betas": _full_betas(job.betas, self.body).tolist(), "stats": summary}
        return arrays, attrs

    def _sequence(self, job, res, per_frame, summary) -> tuple[dict, dict]:
        spec, body = self.spec, self.body
        T, clip = job.frames, job.clip
        betas = np.repeat(_full_betas(job.betas, body)[None], T, 0).astype(np.float32)
        arrays = {"garment_vertices": res.positions.astype(np.float32), "poses": clip.poses.astype(np.float32),
                  "trans": clip.trans.astype(np.float32), "betas": betas}
        if spec.store_rest_frames:
            arrays["rest_garment_vertices"] = _rest_frames(res)
        for k, v in per_frame.items():
            arrays[f"stats/{k}"] = np.asarray(v)
        attrs = {"motion": job.motion, "motion_source": job.motion_source, "fps": float(spec.fps),
                 "split": job.split, "shape_id": job.shape_id, "betas": _full_betas(job.betas, body).tolist(),
                 "frames": T, "start_frame": spec.start_frame, "stats": summary,
                 "retries": summary["solver_retries"], "wall_time": summary["wall_time"]}
        return arrays, attrs


#: Threads writing sequences behind the simulation (``execution.overlap_writes``); the template and
#: the fits keep one thread of their own, in order (a fit needs the template written). The jobs of a
#: pool's last wave end within a few frames of each other; one thread left their writes queued
#: behind the pool's end (BENCHMARKS.md).
SEQUENCE_WRITE_THREADS = 2


class _Writes:
    """The node writes of a pool run: in background threads behind the simulation (``overlap``) or at
    once; outcomes are handed on in the order the jobs ended."""

    def __init__(self, writer: NodeWriter, overlap: bool, on_outcome) -> None:
        self.writer, self.on_outcome = writer, on_outcome
        self.pool = self.lane = None
        if overlap:
            self.pool = ThreadPoolExecutor(max_workers=SEQUENCE_WRITE_THREADS, thread_name_prefix="simgen-write")
            self.lane = ThreadPoolExecutor(max_workers=1, thread_name_prefix="simgen-write-setup")
        self.pending: deque = deque()
        self.outcomes: list = []
        self.error: str | None = None
        self.write_s = 0.0     # [s] spent writing
        self.wait_s = 0.0      # [s] of it the simulation waited for

    def submit(self, job: Job, res) -> None:
        if self.error is not None:
            return
        if self.pool is None:
            self._finish(job, *self._timed(job, res))
        else:
            executor = self.pool if job.kind == "sequence" else self.lane
            self.pending.append((job, executor.submit(self._timed, job, res)))

    def _timed(self, job, res):
        t0 = time.perf_counter()
        try:
            return self.writer.write(job, res), None, time.perf_counter() - t0
        except StoreWriteError as exc:
            return None, str(exc), time.perf_counter() - t0
        except Exception as exc:  # noqa: BLE001 - one job's ground truth failed: that job fails, the pool goes on
            outcome = {**_outcome_base(job), "ok": False,
                       "message": f"its ground truth or statistics failed: {type(exc).__name__}: {exc}"}
            return outcome, None, time.perf_counter() - t0

    def collect(self, wait: bool = False) -> None:
        """Hand on the outcomes of the writes that have ended (all of them with ``wait``)."""
        while self.pending and (wait or self.pending[0][1].done()):
            job, future = self.pending.popleft()
            t0 = time.perf_counter()
            result = future.result()
            self.wait_s += time.perf_counter() - t0
            self._finish(job, *result)

    def _finish(self, job, outcome, error, seconds) -> None:
        self.write_s += seconds
        if self.pool is None:
            self.wait_s += seconds
        if error is not None:
            self.error = self.error or error
            return
        self.outcomes.append(outcome)
        if self.on_outcome is not None:
            self.on_outcome(outcome)
        _injected_kill()

    def close(self) -> None:
        """Wait for the writes submitted (each is committed or not: the store stays consistent)."""
        try:
            self.collect(wait=True)
        finally:
            for executor in (self.pool, self.lane):
                if executor is not None:
                    executor.shutdown(wait=True)


#: Pool frames between two entries of a pool task's ``timeline`` (about 80 for the thesis-tshirt store).
TIMELINE_EVERY = 10


def run_pool_task(task: BatchTask, *, progress=None, on_outcome=None, deadline: float | None = None) -> dict:
    """Simulate a task's jobs in one :class:`simgen.sim.SimulationPool` (:func:`pool_slots` slots, at
    most the task's share) (continuous batching: a slot whose job ended takes the next at the next
    frame, from the task's :class:`JobFeed`, which may hand it other tasks' jobs once its own ran
    out) and write each job as it ends (behind the simulation with ``spec.overlap_writes``).

    progress(cloth_frames_done) after every pool frame; on_outcome(outcome) as each job's write ends
    (in this thread); deadline: a ``time.time()`` value (a wall clock, so that a Ray worker that
    starts late or a retried task keeps the run's budget): no job starts that would not end before
    it (at the pool's recent frame time, writes waited for included), and at it the jobs still
    running are dropped (the first ones start before any frame time is known); the jobs not started
    or dropped come back in ``not_done``, the planned cloth-frames of the dropped ones in
    ``abandoned_cloth_frames``. Jobs whose node is already committed (an earlier attempt of this
    task) are not simulated again; a failed job with attempts left runs again in the same pool
    while the pool will step for longer than the retry takes (:class:`_PoolRetries`). Returns
    {outcomes, error, not_done, abandoned_cloth_frames, slots, wall, cloth_frames, step_s, write_s,
    write_wait, retry_cloth_frames, retry_wall, clock}: slots: the pool's; wall [s] the pool's frames
    (simulation, statistics, host copies); step_s [s] the solver's stepping within them; write_s
    [s] the node writes; write_wait [s] the part of them the simulation waited for; retry_*: the
    later attempts' frames and their share of the wall; clock: time.time() at start, fed (the
    first jobs taken from the feed), ready (pool built), dry (a freed slot first found no job left)
    and end; drain (once dry): the jobs then running, the most and the sum of their pool frames
    left, the pool frames of the jobs still queued in the pool (those no slot could take), and its
    recent frame time [s]; timeline: every ``TIMELINE_EVERY``-th pool frame, [s since clock's start,
    busy slots, frame wall [s], its stepping [s], its solver retries]. A store write failure stops the
    task: ``error`` is one sentence (the store stays consistent; what was committed is kept).
    """
    from simgen.sim import SimulationJob, SimulationPool

    clock = {"start": time.time()}
    _injected_fault()
    quiet_warp()
    spec = task.spec
    loc = Location(task.location)
    body = _load_body(spec.body)
    if task.body_hash is not None and body.hash != task.body_hash:
        raise InputError(f"body model {spec.body} changed since the store was created (hash mismatch)")
    garment = _load_garment(task.garment, spec.body)
    if task.device is not None:
        spec = replace(spec, device=task.device)
    config = spec.solver_config(substeps_factor=task.substeps_factor)
    outcomes: list = []

    def reused(job, commit) -> None:
        outcomes.append({**_outcome_base(job), "ok": True, "checksum": commit["checksum"], "reused": True})
        if on_outcome is not None:
            on_outcome(outcomes[-1])

    # Without a shared feed every job may be committed already (Ray runs a task again after its
    # worker died); a shared one marks those that an earlier run of the task took.
    feed = task.feed if task.feed is not None else JobFeed({task.name: list(task.jobs)}, marked=True)
    feed.start(task.name)
    source = _Source(feed, task.name, loc, reused)
    report = {"outcomes": outcomes, "error": None, "not_done": [], "abandoned_cloth_frames": 0, "slots": 0,
              "wall": 0.0, "cloth_frames": 0, "step_s": 0.0, "write_s": 0.0, "write_wait": 0.0,
              "clock": clock, "gpu_memory_high_bytes": None, "retry_cloth_frames": 0, "retry_wall": 0.0,
              "timeline": []}
    first = source.take(min(pool_slots(spec, config.device, garment), max(len(task.jobs), 1)))
    clock["fed"] = time.time()
    if not first:
        clock["ready"] = clock["end"] = time.time()
        return report
    slots = len(first)
    pool = SimulationPool(garment, body, slots, config, fps=spec.fps)
    retries = _PoolRetries(spec, task.attempt, pool, on_outcome, source.waiting)
    for job in first:
        retries.submit(job)
    writes = _Writes(NodeWriter(spec, config, garment, body, loc, slots), spec.overlap_writes, retries.outcome)

    def top_up() -> None:
        # A slot takes a job from the feed only when it frees up (the others' pools may take the rest);
        # under a deadline the pool refuses each job that would not end in time.
        free = pool.num_slots - pool.busy - pool.queued
        if free > 0:
            for job in source.take(free):
                retries.submit(job)
            if source.dry and "dry" not in clock:
                clock["dry"] = time.time()   # the pool drains from here, with this work in flight:
                pool.fill()                  # (the jobs just taken start now, as the next step would)
                left = [n for _, n in pool.frames_left()]
                report["drain"] = {"jobs": len(left), "frames_left_max": max(left, default=0),
                                   "frames_left_sum": sum(left), "queued_frames": pool.queued_frames,
                                   "frame_s": pool.recent_frame_time()}

    def accept(job, frames) -> bool:
        frame_s = pool.recent_frame_time()
        if deadline is None or frame_s is None:
            return True
        waited = writes.wait_s / max(pool.frames_run, 1)
        return time.time() + frames * (frame_s + waited) <= deadline

    pool.accept = accept
    pool.gate = functools.partial(_outlier, spec)
    abandoned: list = []
    clock["ready"] = time.time()
    try:
        while True:
            top_up()
            if not (pool.busy or pool.queued):
                writes.collect(wait=True)     # the last writes may send failed jobs back into the pool
                top_up()
                if writes.error is not None or not (pool.busy or pool.queued):
                    break
            stepped = pool.frames_run
            for job, res in pool.step():
                res = _injected_divergence(job, res)
                retries.ended(job, res)
                writes.submit(job, res)
            if pool.frames_run > stepped and pool.frames_run % TIMELINE_EVERY == 0:
                f = pool.last_frame
                report["timeline"].append([round(time.time() - clock["start"], 2), f["busy"], round(f["wall"], 4),
                                           round(f["step"], 4), f["retries"]])
            writes.collect()
            if progress is not None:
                progress(pool.cloth_frames)
            if writes.error is not None:
                pool.refused += pool.drop_queue()
                break
            if deadline is not None and time.time() > deadline:
                # Past the budget (the first jobs start before any frame time is known): stop.
                pool.refused += pool.drop_queue()
                abandoned = pool.abandon()
                break
    finally:
        writes.close()
        pool.refused += pool.drop_queue()   # retries of the writes that ended after the last frame
        pool.accept = None   # the closure holds the pool: free its device memory with the pool
        clock["end"] = time.time()
    report.update(not_done=pool.refused + abandoned + feed.rest(task.name),
                  abandoned_cloth_frames=sum(job_cloth_frames(spec, [j]) for j in abandoned), slots=slots,
                  outcomes=outcomes + writes.outcomes, error=writes.error, wall=pool.wall,
                  cloth_frames=pool.cloth_frames, step_s=pool.step_time, write_s=writes.write_s,
                  write_wait=writes.wait_s, gpu_memory_high_bytes=_memory_high(config.device),
                  retry_cloth_frames=retries.cloth_frames, retry_wall=retries.wall)
    return report


class _Source:
    """A task's side of its :class:`JobFeed`: jobs whose node is not committed yet. A marked job is
    looked up in the store first (reused(job, commit) for a committed one); once the feed has run
    dry it is not asked again (no blocking call per frame at a pool's end)."""

    def __init__(self, feed, name: str, loc: Location, reused) -> None:
        self.feed, self.name, self.loc, self.reused = feed, name, loc, reused
        self.dry = False

    def take(self, n: int) -> list:
        out: list = []
        while len(out) < n and not self.dry:
            batch = self.feed.take(self.name, n - len(out))
            self.dry = not batch
            for job, marked in batch:
                commit = self.loc.committed(_node_rel(job)) if marked else None
                if commit is None:
                    out.append(job)
                else:
                    self.reused(job, commit)
        return out

    def waiting(self, protocol_frames: int) -> float:
        """Cloth-frames this task's pool can still expect from the feed (:meth:`JobFeed.share_left`)."""
        return 0.0 if self.dry else self.feed.share_left(protocol_frames)


class _PoolRetries:
    """Sends a task's failed jobs back into its pool at twice the substeps while the pool, by the
    work waiting for its slots (queued in the pool or left in its feed: module doc) and the work in
    flight, will step for longer than the retry takes (:func:`pool_frames_left`).

    spec: the store's spec; attempt: the task's (its pool's substeps); pool: the SimulationPool;
    on_outcome: the caller's, handed every outcome after this has seen it; fed(protocol_frames) ->
    cloth-frames the pool can still expect from its feed. ``cloth_frames`` and
    ``wall`` [s]: the frames of the later attempts that ended, and their share of the pool's time.
    """

    def __init__(self, spec, attempt: int, pool, on_outcome, fed) -> None:
        self.spec, self.attempt, self.pool, self.on_outcome = spec, int(attempt), pool, on_outcome
        self.fed = fed
        self.jobs: dict = {}     # key -> the Job of its latest attempt
        self.cloth_frames = 0
        self.wall = 0.0

    def submit(self, job: Job) -> None:
        from simgen.sim import SimulationJob

        self.jobs[job.key] = job
        factor = 2 ** (job.attempt - self.attempt)
        self.pool.submit(SimulationJob(job.clip, betas=job.betas, key=job.key, substeps_factor=factor), tag=job)

    def ended(self, job: Job, res) -> None:
        if job.attempt > self.attempt:
            self.cloth_frames += job_cloth_frames(self.spec, [job])
            self.wall += float(getattr(res, "metadata", {}).get("wall_share", 0.0))

    def outcome(self, o: dict) -> None:
        job = self.jobs[f"{o['kind']}:{o['id']}"]
        again = (not o["ok"] and not o.get("waiting") and job.kind != "template"
                 and job.attempt < self.spec.max_attempts and self._ends_in_time(job))
        if again:
            o["retry"] = "pool"
        if self.on_outcome is not None:
            self.on_outcome(o)       # the failure is in the manifest before its retry starts
        if again:
            self.submit(replace(job, attempt=job.attempt + 1))

    def _ends_in_time(self, job: Job) -> bool:
        """The retry of ``job`` ends before the pool would: the pool frames it takes (its
        cloth-frames times its substeps over the pool's) are at most the pool's life left
        (:func:`pool_frames_left`). A retry that outlasted the pool would step on alone (an idle
        slot costs a good part of a busy one: BENCHMARKS.md) and hold its GPU past the other pools;
        the driver runs it in a small pool on the first free worker instead."""
        need = job_cloth_frames(self.spec, [job]) * 2 ** (job.attempt + 1 - self.attempt)
        waiting = self.pool.queued_frames + self.fed(self.spec.protocol_frames())
        return need <= pool_frames_left(waiting, [n for _, n in self.pool.frames_left()], self.pool.num_slots)


def pool_frames_left(waiting: float, in_flight: list, slots: int) -> float:
    """Pool frames a pool of ``slots`` slots will still step, estimated from the cloth-frames waiting
    for its slots (queued or in its feed) and the pool frames each job in flight has left. With
    nothing waiting: its longest job in flight. Else the waiting work spread over every slot after
    the work in flight, then the drain, in which the jobs started last run on for about as long as
    the jobs in flight have left on average (a full pool's work in flight is left about uniformly
    between 0 and L: the pool ends about L after its feed runs dry, as it does); never less than
    the longest job in flight. It overestimates when the jobs started last are shorter than those
    in flight (the feed hands out the longest first)."""
    if waiting <= 0:
        return max(in_flight, default=0)
    if not in_flight:
        return waiting / slots
    drain = sum(in_flight) / len(in_flight)
    return max(max(in_flight), (waiting + sum(in_flight)) / slots + drain)


def _memory_high(device: str) -> int | None:
    if not str(device).startswith("cuda"):
        return None
    import warp as wp

    return int(wp.get_mempool_used_mem_high(device))


def _claims_injection(variable: str) -> bool:
    """Testing hooks: True for the first process to find the file named by the environment
    ``variable`` missing (it creates it, so the injection happens once per run)."""
    import os

    marker = os.environ.get(variable)
    if not marker:
        return False
    try:
        with open(marker, "x"):
            return True
    except FileExistsError:
        return False


def _injected_fault() -> None:
    # SIMGEN_DATASET_FAULT_ONCE=FILE: the first batch fails at its start, as a crashed task would.
    if _claims_injection("SIMGEN_DATASET_FAULT_ONCE"):
        raise RuntimeError("injected fault (SIMGEN_DATASET_FAULT_ONCE)")


def _injected_divergence(job: Job, res):
    # SIMGEN_DATASET_DIVERGE_ONCE=FILE: the template's first attempt diverges (in whichever process
    # runs it), a failure that only the driver retries.
    if job.kind == "template" and job.attempt == 1 and _claims_injection("SIMGEN_DATASET_DIVERGE_ONCE"):
        from simgen.sim import SimulationFailure

        return SimulationFailure(job.key, "diverged (SIMGEN_DATASET_DIVERGE_ONCE)", "relax", 0)
    return res


def _injected_kill() -> None:
    # SIMGEN_DATASET_KILL_ONCE=FILE: the first process to commit a node then dies by SIGKILL (no
    # exception, no cleanup: what a killed Ray worker or an out-of-memory kill leaves).
    if _claims_injection("SIMGEN_DATASET_KILL_ONCE"):
        import os
        import signal

        os.kill(os.getpid(), signal.SIGKILL)


def _node_rel(job: Job) -> str:
    if job.kind == "template":
        return "template"
    return f"{'fit' if job.kind == 'fit' else 'sequences'}/{job.id}"


def _full_betas(betas, body) -> np.ndarray:
    b = np.zeros(max(body.num_betas, 1))
    v = np.asarray(betas if betas is not None else [], dtype=np.float64).reshape(-1)
    b[:len(v)] = v
    return b[:body.num_betas] if body.num_betas else b


def _stored_template_smoothed(loc: Location) -> np.ndarray | None:
    if loc.committed("template") is None:
        return None
    import zarr

    return np.asarray(zarr.open_group(loc.url("template"), mode="r")["smoothed"][...], dtype=np.float64)
