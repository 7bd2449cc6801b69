"""generate_dataset(): plan the jobs of a spec, run them in batches (locally or on Ray), keep the store consistent.

One store per garment (docs/architecture.md, "Dataset store"). For each store the driver:

1. opens or creates it (:class:`simgen.dataset.store.DatasetStore`; a store made with a different
   content key is refused), takes its lock and reconciles it with the manifest (resume after kill -9);
2. plans the jobs (:func:`plan_jobs`) and keeps those whose node is not in the manifest;
3. runs a first batch with the template relaxation and the pending fits, then the pending sequences
   in batches of ``execution.batch_size`` clips of similar length (longest first); locally, the
   write phase of a batch runs in a background thread while the next batch simulates
   (``execution.overlap_writes``, :class:`_LocalExecutor`); results are entered in batch order;
4. enters every outcome into the manifest (rewritten atomically after each batch) and re-queues a
   failed job (diverged, or a sequence with a strain outlier: ``execution.retry_strain_outliers``)
   into a later batch with the substep halved, up to ``max_attempts``.

``max_sequences`` and ``time_budget`` make a run do a part of the plan (the store stays resumable:
the next run continues). With ``ray`` the batches become Ray tasks (:mod:`simgen.dataset.distributed`).
"""

from __future__ import annotations

import hashlib
import json
import time
from collections import deque
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import asdict, dataclass, field

import numpy as np

from simgen.dataset.execute import (BatchTask, Job, job_cloth_frames, rest_clip, run_batch, simulate_batch_task,
                                    write_batch)
from simgen.dataset.spec import DatasetSpec, load_spec
from simgen.dataset.storage import FORMAT_VERSION, Location, StoreWriteError
from simgen.dataset.store import DatasetStore
from simgen.errors import GenerationError, InputError

__all__ = ["generate_dataset", "plan_jobs", "load_clips", "StoreReport", "GenerationError", "garment_hash",
           "root_attrs"]


@dataclass
class StoreReport:
    """What one run did to one store."""

    path: str
    garment: str
    planned_sequences: int
    planned_fits: int
    done_before: int
    written: int = 0
    failed: dict = field(default_factory=dict)
    pending: int = 0
    cloth_frames: int = 0
    # Timings. wall is the run's wall clock; the others are summed over batches, phase by phase. With
    # execution.overlap_writes (local runs) a batch is written while the next one simulates, so
    # simulate_wall + write_wall exceeds wall by the write time hidden that way; write_wait is the
    # part of write_wall the driver waited for (all of it without the overlap, and on Ray).
    wall: float = 0.0
    simulate_wall: float = 0.0  # [s] summed over batches: simulate_batch calls
    step_wall: float = 0.0      # [s] of which the solver's stepping (the rest: posing, statistics, copies)
    write_wall: float = 0.0     # [s] ground truth, statistics and store writes
    write_wait: float = 0.0     # [s] of write_wall not hidden behind a simulation
    # Jobs simulated again (divergence or a strain outlier), and what the batches of those later
    # attempts cost: their cloth-frames (also in cloth_frames) and simulation wall [s].
    retried: int = 0
    retry_cloth_frames: int = 0
    retry_simulate_wall: float = 0.0
    stopped: str | None = None
    reconcile: dict = field(default_factory=dict)

    @property
    def cloth_frames_per_second(self) -> float:
        return self.cloth_frames / self.wall if self.wall > 0 else 0.0

    def to_dict(self) -> dict:
        d = asdict(self)
        d["cloth_frames_per_second"] = self.cloth_frames_per_second
        return d


def garment_hash(garment) -> str:
    """SHA-256 of the garment's vertices, faces and skin weights (float32/int32 bytes) and, where it
    has one, its waistband (what is tied to the body changes the simulation)."""
    h = hashlib.sha256()
    for a, dt in ((garment.vertices, np.float32), (garment.faces, np.int32), (garment.skin_weights, np.float32)):
        h.update(np.ascontiguousarray(a, dtype=dt).tobytes())
    band = (garment.metadata or {}).get("waistband")
    if band:
        h.update(json.dumps(band, sort_keys=True).encode())
    return h.hexdigest()


def root_attrs(spec: DatasetSpec, garment, body) -> dict:
    """The root attrs of the store of ``garment`` (see :mod:`simgen.dataset.store`)."""
    from simgen import __version__

    config = spec.solver_config()
    material = config.resolve_material(garment)
    key = spec.content_key(garment.name)
    key["body_hash"] = body.hash
    key["garment_hash"] = garment_hash(garment)
    content_hash = hashlib.sha256(json.dumps(key, sort_keys=True).encode()).hexdigest()
    return {
        "format_version": FORMAT_VERSION,
        "simgen_version": __version__,
        "spec": spec.to_dict(),
        "content_key": key,
        "content_hash": content_hash,
        "body": {"id": body.model_id, "hash": body.hash, "source": spec.body, "num_betas": body.num_betas},
        "garment": {"name": garment.name, "hash": key["garment_hash"], "vertices": garment.num_vertices,
                    "triangles": garment.num_triangles},
        "material": material.to_dict(),
        "solver": {"fps": spec.fps, "substeps": spec.substeps, "dt": 1.0 / spec.fps / spec.substeps,
                   "relax_frames": spec.relax_frames, "ramp_frames": spec.ramp_frames,
                   "rest_frames": spec.rest_frames,
                   "config": json.loads(json.dumps(asdict(config.solver), default=float))},
    }


def load_clips(spec: DatasetSpec, body) -> list[tuple[object, object]]:
    """(MotionEntry, MotionClip) of every motion: resampled to the spec's fps, trimmed to
    [start_frame, start_frame + max_frames). InputError for files that fail to load or clips
    shorter than start_frame + 1."""
    from simgen.motion.clip import MotionClip
    from simgen.motion.library import load_motion
    from simgen.motion.motion_file import load_motion_file
    from simgen.motion.ops import resample

    out = []
    for entry in spec.motions():
        if entry.source == "library":
            clip = load_motion(entry.id)
        else:
            clip = load_motion_file(entry.source, body=body, name=entry.id)
        if abs(clip.fps - spec.fps) > 1e-6:
            clip = resample(clip, spec.fps)
        start = spec.start_frame
        if start >= clip.num_frames:
            raise InputError(f"spec {spec.source}: field 'motions.start_frame' = {start} is past the end of motion "
                             f"{entry.id!r} ({clip.num_frames} frames)")
        stop = clip.num_frames if spec.max_frames == 0 else min(clip.num_frames, start + spec.max_frames)
        if start or stop < clip.num_frames:
            clip = MotionClip(clip.name, clip.fps, clip.poses[start:stop], clip.trans[start:stop], dict(clip.meta))
        out.append((entry, clip))
    return out


def plan_jobs(spec: DatasetSpec, garment_name: str, body) -> list[Job]:
    """Every job of one store in plan order: template, fits (shape order), sequences (motion-major)."""
    nb = max(body.num_betas, 1)
    shapes = spec.shapes()
    for s in shapes:
        if len(s.betas) > body.num_betas:
            raise InputError(f"spec {spec.source}: shape {s.id!r} has {len(s.betas)} betas but body model "
                             f"{body.name!r} has {body.num_betas} shape components")

    def betas_of(s):
        b = np.zeros(nb)
        b[:len(s.betas)] = s.betas
        return b[:body.num_betas] if body.num_betas else b

    rc = rest_clip(spec.fps)
    jobs = [Job("template", "template", rc, np.zeros(body.num_betas))]
    jobs += [Job("fit", s.id, rc, betas_of(s), shape_id=s.id) for s in shapes]
    for entry, clip in load_clips(spec, body):
        for s in shapes:
            jobs.append(Job("sequence", f"{entry.id}__{s.id}", clip, betas_of(s), shape_id=s.id, motion=entry.id,
                            split=entry.split, motion_source=entry.source))
    return jobs


def _batches(spec: DatasetSpec, jobs: list[Job], attempt: int) -> list[list[Job]]:
    """Setup jobs (template, fits) in one batch; sequences longest first in batches of batch_size."""
    setup = [j for j in jobs if j.kind != "sequence"]
    seqs = sorted((j for j in jobs if j.kind == "sequence"), key=lambda j: -j.frames)
    out = [setup] if setup else []
    bs = spec.batch_size
    out += [seqs[i:i + bs] for i in range(0, len(seqs), bs)]
    return out


@dataclass
class _Pending:
    """A batch of the local executor past its simulation: waiting for the writer, being written
    (future) or failed (error, raised when its result is asked for)."""

    task: BatchTask
    simulated: object = None
    future: Future | None = None
    error: BaseException | None = None


class _LocalExecutor:
    """Runs the batches in this process; results come back in submission order.

    The simulation phase (:func:`simulate_batch_task`) runs in the calling thread when a result is
    asked for, so progress is live and Warp stays on one thread. With ``overlap`` (the spec's
    ``execution.overlap_writes``) the write phase (:func:`write_batch`: ground truth, statistics,
    Zarr, commits; host work only) runs in one background thread, one batch at a time:
    :meth:`next_result` starts the write of the oldest simulated batch, simulates the next queued
    batch meanwhile, then waits for that write and returns its result. The driver keeps
    ``parallel`` = 2 batches in flight, so batch k is written while batch k+1 simulates, and a
    batch's write starts only once the driver has recorded the one before it: when a write fails,
    no later batch has been written. Without ``overlap``: :func:`run_batch`, one batch at a time.

    ``simultaneous`` is how many simulations run at the same time (1 here; one per worker on Ray):
    what the driver's time-budget estimate divides the throughput by.

    An exception of a simulation is raised when that batch's result is asked for (the batch being
    written is returned first), one of a write when its result is; a :class:`StoreWriteError` comes
    back in the result's ``error`` as from :func:`run_batch`. :meth:`drain` drops the batches not
    written and waits for the write in progress (the driver calls it before it releases the store's
    lock); :meth:`close` drains and stops the thread.
    """

    simultaneous = 1

    def __init__(self, overlap: bool = True) -> None:
        self.overlap = overlap
        self.parallel = 2 if overlap else 1
        self.queue: deque = deque()    # (task, progress): submitted, not simulated yet
        self.pending: deque = deque()  # _Pending, oldest first; only the oldest may be being written
        self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="simgen-write") if overlap else None

    def submit(self, task: BatchTask, progress) -> None:
        self.queue.append((task, progress))

    def in_flight(self) -> int:
        return len(self.queue) + len(self.pending)

    def _start_write(self) -> None:
        head = self.pending[0] if self.pending else None
        if head is not None and head.future is None and head.error is None:
            head.future = self._pool.submit(write_batch, head.simulated)
            head.simulated = None

    def next_result(self):
        if self._pool is None:
            task, progress = self.queue.popleft()
            return task, run_batch(task, progress=progress)
        self._start_write()
        while self.queue and len(self.pending) < self.parallel and not any(p.error for p in self.pending):
            task, progress = self.queue.popleft()
            try:
                simulated = simulate_batch_task(task, progress=progress)
            except Exception as exc:
                if not self.pending:
                    raise
                self.pending.append(_Pending(task, error=exc))  # raised in order, after the batch being written
                break
            self.pending.append(_Pending(task, simulated=simulated))
            self._start_write()
        head = self.pending[0]
        if head.error is not None:
            self.pending.popleft()
            raise head.error
        t0 = time.perf_counter()
        try:
            result = head.future.result()
        finally:
            if head.future.done():  # else (interrupted while waiting) drain() waits for it
                self.pending.popleft()
        waited = time.perf_counter() - t0  # the part of this batch's write the simulation meanwhile did not hide
        return head.task, {**result, "write_wait": min(waited, result["write_s"])}

    def drain(self) -> None:
        """Drop the batches not written yet and wait for the write in progress, if any."""
        self.queue.clear()
        pending, self.pending = list(self.pending), deque()
        for p in pending:
            if p.future is not None:
                try:
                    p.future.result()
                except Exception:  # noqa: BLE001 - an error is already on its way up; the store stays consistent
                    pass

    def close(self) -> None:
        self.drain()
        if self._pool is not None:
            self._pool.shutdown(wait=True)
            self._pool = None


def generate_dataset(spec, out: str | None = None, *, ray: str | None = None, max_sequences: int | None = None,
                     time_budget: float | None = None, progress=None, log=None) -> list[StoreReport]:
    """Generate (or resume) the stores of a spec. Returns one :class:`StoreReport` per garment.

    spec: :class:`DatasetSpec`, a TOML path or a preset name; out: store folder or fsspec URL
      (default: the spec's output.path); ray: None (local), "local" (a Ray instance on this
      machine) or a Ray cluster address; max_sequences: at most this many new sequences per
      store in this run; time_budget [s]: start no batch that would not finish in time (estimated
      from the throughput so far); progress(done, total) in cloth-frames; log(str): messages.
    Raises InputError for bad input, StoreWriteError when the store cannot be written (the store
    stays consistent and resumable), GenerationError when a Ray task fails beyond its retries.
    """
    from simgen._warp_log import quiet_warp
    from simgen.dataset.execute import _load_body, _load_garment

    quiet_warp()
    spec = load_spec(spec)
    if max_sequences is not None and (isinstance(max_sequences, bool) or max_sequences < 0):
        raise InputError(f"--max-sequences must be >= 0, got {max_sequences}")
    if time_budget is not None and not time_budget > 0:
        raise InputError(f"--time-budget must be > 0 seconds, got {time_budget}")
    say = log or (lambda msg: None)
    body = _load_body(spec.body)
    garments = [_load_garment(name, spec.body) for name in spec.garments]
    plans = [plan_jobs(spec, g.name, body) for g in garments]  # all input checked before anything is written
    executor = None
    t_start = time.perf_counter()
    reports = []
    try:
        for garment, plan in zip(garments, plans):
            loc = Location(spec.output_path(garment.name, out))
            store = DatasetStore.open_for_writing(loc, root_attrs(spec, garment, body))
            try:
                rec = store.reconcile()
                if any(rec.values()):
                    say(f"{loc.root}: resumed ({', '.join(f'{k} {v}' for k, v in rec.items() if v)})")
                seq_total = sum(j.kind == "sequence" for j in plan)
                done_before = len(store.manifest["sequences"])
                pending = [j for j in plan if not store.done(j.kind, j.id)]
                seqs = [j for j in pending if j.kind == "sequence"]
                if max_sequences is not None and len(seqs) > max_sequences:
                    keep = {j.id for j in seqs[:max_sequences]}
                    pending = [j for j in pending if j.kind != "sequence" or j.id in keep]
                report = StoreReport(path=loc.root, garment=garment.name, planned_sequences=seq_total,
                                     planned_fits=len(spec.shapes()), done_before=done_before, reconcile=rec)
                if executor is None:
                    executor = _make_executor(ray, spec)
                device = getattr(executor, "device", None)
                _drive(spec, store, garment, body, pending, executor, report, progress, time_budget, t_start, say,
                       device)
                report.pending = seq_total - len(store.manifest["sequences"])
                reports.append(report)
            finally:
                if executor is not None and hasattr(executor, "drain"):
                    executor.drain()  # no write of ours may run once the lock is released
                store.release()
    finally:
        if executor is not None:
            executor.close()
    return reports


def _make_executor(ray: str | None, spec: DatasetSpec):
    if ray is None:
        return _LocalExecutor(overlap=spec.overlap_writes)
    from simgen.dataset.distributed import RayExecutor

    return RayExecutor(ray, spec)


def _budget_rate(report: StoreReport, simultaneous: int) -> float:
    """Cloth-frames per second that the time budget's estimate divides by, from the batches whose
    results came back.

    One simulation at a time (local): a batch costs the driver its simulation plus the part of its
    write not hidden behind the next simulation. Not the wall clock: with the writes overlapped, the
    result of batch k comes back after batch k+1 has simulated, so the wall clock then holds a batch
    more than the results (a 2-batch run would read half its real rate). Several workers (Ray):
    the throughput of all together, cloth-frames over wall time.
    """
    if simultaneous == 1:
        busy = report.simulate_wall + report.write_wait
        return report.cloth_frames / busy if busy > 0 else 0.0
    return report.cloth_frames_per_second


def _drive(spec, store, garment, body, pending, executor, report, progress, time_budget, t_start, say, device):
    batches = deque((1, b) for b in _batches(spec, pending, 1))
    total = [sum(job_cloth_frames(spec, b) for _, b in batches)]
    done = [0]       # cloth-frames of the batches whose result came back
    submitted = [0]  # cloth-frames of the batches submitted (a batch's progress starts there)
    shown = [0]      # progress never goes back (a result may come back after the next batch simulated)
    rate = [0.0]  # cloth-frames per second measured so far (0: unknown)
    # Simulations running at the same time: the local executor simulates one batch at a time even
    # while it writes another (parallel 2); Ray runs `parallel` batches at once.
    simultaneous = getattr(executor, "simultaneous", executor.parallel)
    t0 = time.perf_counter()

    def show(n):
        if progress is not None:
            shown[0] = max(shown[0], min(n, total[0]))
            progress(shown[0], total[0])

    show(0)

    def batch_progress(base):
        def cb(n):
            show(base + n)
        return cb

    while batches or executor.in_flight():
        while batches and executor.in_flight() < executor.parallel:
            attempt, jobs = batches[0]
            frames = job_cloth_frames(spec, jobs)
            if time_budget is not None and (report.cloth_frames or executor.in_flight()):
                elapsed = time.perf_counter() - t_start
                # rate is the throughput of all workers together; one batch runs on one of them. Locally
                # (one simulation at a time) that is frames / rate, writes included; with the overlap
                # the last batch's write may still run past the estimate (drained before returning).
                est = frames * simultaneous / rate[0] if rate[0] > 0 else 0.0
                if elapsed + est > time_budget:
                    report.stopped = f"time budget of {time_budget:g} s reached"
                    batches.clear()
                    break
            batches.popleft()
            task = BatchTask(location=store.loc.root if store.loc.is_local else store.loc.url(), spec=spec,
                             garment=garment.name, jobs=jobs, attempt=attempt, device=device, body_hash=body.hash)
            executor.submit(task, batch_progress(submitted[0]))
            submitted[0] += frames
        if not executor.in_flight():
            break
        task, result = executor.next_result()
        done[0] += job_cloth_frames(spec, task.jobs)
        report.cloth_frames += result["cloth_frames"]
        report.simulate_wall += result["wall"]
        report.step_wall += result.get("step_s", 0.0)
        report.write_wall += result.get("write_s", 0.0)
        report.write_wait += result.get("write_wait", result.get("write_s", 0.0))
        if task.attempt > 1:
            report.retry_cloth_frames += result["cloth_frames"]
            report.retry_simulate_wall += result["wall"]
        report.wall = time.perf_counter() - t0
        rate[0] = _budget_rate(report, simultaneous)
        retry, waiting = [], []
        by_key = {f"{j.kind}:{j.id}": j for j in task.jobs}
        for o in result["outcomes"]:
            if o.get("waiting"):
                # Not simulated for its own sake (the template of its batch failed): again, same attempt.
                waiting.append(by_key[f"{o['kind']}:{o['id']}"])
                continue
            store.record(o)
            if o["ok"]:
                report.failed.pop(f"{o['kind']}:{o['id']}", None)
                if o["kind"] == "sequence" and not o.get("reused"):
                    report.written += 1
            else:
                job = by_key[f"{o['kind']}:{o['id']}"]
                if job.attempt < spec.max_attempts:
                    say(f"{job.key} failed on attempt {job.attempt} ({o['message']}); retrying with "
                        f"{spec.substeps * 2 ** job.attempt} substeps")
                    retry.append(Job(**{**job.__dict__, "attempt": job.attempt + 1}))
                    report.retried += 1
                else:
                    report.failed[job.key] = o["message"]
        if "template:template" in report.failed:
            for job in waiting:
                report.failed[job.key] = "the template relaxation failed"
                store.record({"ok": False, "kind": job.kind, "id": job.id, "attempt": job.attempt,
                              "message": "the template relaxation failed"})
            waiting = []
        store.save_manifest()
        show(done[0])
        if result["error"]:
            raise StoreWriteError(result["error"])
        # The template's retry runs next, alone; the fits waiting for it follow at their own attempt.
        for job in (j for j in retry if j.kind == "template"):
            batches.appendleft((job.attempt, [job]))
            total[0] += job_cloth_frames(spec, [job])
        retry = [j for j in retry if j.kind != "template"] + waiting
        for attempt in sorted({j.attempt for j in retry}):
            group = [j for j in retry if j.attempt == attempt]  # a batch shares its substeps
            for b in _batches(spec, group, attempt):
                batches.append((attempt, b))
                total[0] += job_cloth_frames(spec, b)
