"""generate_dataset(): plan the jobs of a spec, run them in simulation pools (locally or on Ray), keep
the store consistent.

One store per garment (docs/architecture.md, "Dataset store"). For each store the driver:

1. opens or creates it (:class:`simgen.dataset.store.DatasetStore`; a store made with a different
   content key is refused), takes its lock and reconciles it with the manifest (resume after kill -9);
2. plans the jobs (:func:`plan_jobs`) and keeps those whose node is not in the manifest;
3. runs them in one simulation pool (:func:`simgen.dataset.execute.run_pool_task`: continuous
   batching, each finished job written in the background while the pool steps on): the template
   relaxation first, then the fits, then the sequences longest first, each starting as a slot
   frees up; on Ray the jobs are dealt into one pool per GPU worker
   (:mod:`simgen.dataset.distributed`);
4. enters every outcome into the manifest (rewritten atomically every few seconds and after each
   pool); a failed job (diverged, or a sequence with a strain or depth outlier, stopped at that
   frame: ``execution.retry_strain_outliers``, ``retry_depth_outliers``) runs again with the
   substep halved, up to ``max_attempts``:
   in the same pool (a slot at twice the substeps beside the others) while the pool will step for
   longer than the retry takes, else in a later pool, with the other failures of its attempt that
   are known by then, started as soon as a worker is free (on Ray, while the other pools still
   step); a failed template relaxation runs again alone first, since the fits need it, and fits
   that ended before it was written run again after it.

``max_sequences`` and ``time_budget`` make a run do a part of the plan (the store stays resumable:
the next run continues); under a time budget a pool starts no job that it would not finish in time,
at its mean frame time so far, and drops the jobs still running when the budget is spent.
"""

from __future__ import annotations

import hashlib
import json
import time
from collections import deque
from dataclasses import asdict, dataclass, field, replace

import numpy as np

from simgen.dataset.execute import BatchTask, Job, job_cloth_frames, rest_clip, run_pool_task
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
    slots: int = 0              # the largest simulation pool's slots
    # Timings. wall is the run's wall clock; the others are summed over pools. With
    # execution.overlap_writes a job is written while the pool steps on, so simulate_wall +
    # write_wall exceeds wall by the write time hidden that way; write_wait is the part of write_wall
    # the simulation waited for (all of it without the overlap).
    wall: float = 0.0
    simulate_wall: float = 0.0  # [s] summed over pools: their frames
    step_wall: float = 0.0      # [s] of which the solver's stepping (the rest: posing, statistics, copies)
    write_wall: float = 0.0     # [s] ground truth, statistics and store writes
    write_wait: float = 0.0     # [s] of write_wall not hidden behind the simulation
    # Jobs simulated again (divergence, a strain or depth outlier), and what the pools of those later
    # attempts cost: their cloth-frames (also in cloth_frames) and simulation wall [s]; one entry
    # per such failed attempt: {job, attempt, message, at [s] from the run's start}.
    retried: int = 0
    retry_cloth_frames: int = 0
    retry_simulate_wall: float = 0.0
    failed_attempts: list = field(default_factory=list)
    stopped: str | None = None
    reconcile: dict = field(default_factory=dict)
    # [s] from the run's start until the executor could take tasks (Ray started; None without Ray).
    executor_ready: float | None = None
    # One entry per pool task, by round: {round, worker (Ray: node and GPU ids), beside (started
    # in the share of a GPU that a busy pool left), submitted, start, fed, ready, [dry,] end [s]
    # from the run's start (handed to the executor, task began, its first jobs taken from the feed,
    # pool built, a freed slot first found no job left: the pool drains from there, last write
    # ended), cloth_frames,
    # retry_cloth_frames and retry_wall [s] (its in-pool retries: frames, share of the pool's
    # time), slots, gpu_memory_high_bytes (Warp's pool at its fullest in the task's process
    # so far: a later task of the same process reports at least an earlier one's), [drain: the
    # work in flight when the pool found the feed dry: {jobs, frames_left_max, frames_left_sum,
    # queued_frames, frame_s}], timeline (every 10th pool frame: [s from the run's start, busy
    # slots, frame wall [s], its stepping [s], its solver retries])}.
    tasks: list = field(default_factory=list)

    @property
    def cloth_frames_per_second(self) -> float:
        return self.cloth_frames / self.wall if self.wall > 0 else 0.0

    @property
    def startup_s(self) -> float | None:
        """[s] from the run's start until the last pool of the first round was built (loading,
        Ray's workers, kernel loads and allocation): the run's start-up."""
        first = [t["ready"] for t in self.tasks if t["round"] == 1]
        return max(first) if first else None

    def to_dict(self) -> dict:
        d = asdict(self)
        d["cloth_frames_per_second"] = self.cloth_frames_per_second
        d["startup_s"] = self.startup_s
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


#: [s] The driver rewrites the manifest at most this often while a pool runs (and after each pool).
MANIFEST_EVERY_S = 5.0


def _plan_order(jobs: list[Job]) -> list[Job]:
    """Template, fits (plan order), then sequences longest first (the pool's tail stays short)."""
    rank = {"template": 0, "fit": 1, "sequence": 2}
    return sorted(jobs, key=lambda j: (rank[j.kind], -j.frames if j.kind == "sequence" else 0))


def _next_jobs(queue: list[Job], first: bool, template_running: bool) -> list[Job]:
    """The jobs of the next pool, taken out of ``queue``: at first every job of the lowest attempt;
    a template retry alone (later, or first when a rerun resumes it at a later attempt than the
    rest: the fits waiting for it need it written), else every job of the lowest attempt (a pool
    shares its substep). While a template pool runs, the fits wait (none is taken)."""
    candidates = [j for j in queue if not (template_running and j.kind == "fit")]
    if not candidates:
        return []
    low = min(j.attempt for j in candidates)
    template = next((j for j in candidates if j.kind == "template"), None)
    if template is not None and (not first or template.attempt > low):
        chosen = [template]
    else:
        chosen = [j for j in candidates if j.attempt == low]
    for j in chosen:
        queue.remove(j)
    return _plan_order(chosen)


def _split(jobs: list[Job], parts: int) -> list[list[Job]]:
    """Jobs in at most ``parts`` groups of similar work: the template and the fits together in the
    first (a fit is written only after the template), the sequences dealt round-robin, longest first."""
    setup = [j for j in jobs if j.kind != "sequence"]
    seqs = [j for j in jobs if j.kind == "sequence"]
    parts = max(1, min(parts, len(seqs) + bool(setup)))
    groups = [list(setup)] + [[] for _ in range(parts - 1)]
    for i, job in enumerate(seqs):
        groups[(i + bool(setup)) % parts].append(job)
    return [g for g in groups if g]


class _LocalExecutor:
    """Runs each task in this process, one at a time, when the driver asks for the next to end
    (:func:`run_pool_task`); the outcomes reach the driver as the jobs' writes end."""

    parallel, beside = 1, 0

    def __init__(self) -> None:
        self._waiting: deque = deque()
        self._count = 0

    def start(self, tasks, budget_s, on_outcome, progress, beside: bool = False) -> list[int]:
        """Queue the pool tasks of one round (each runs its own jobs); their handles."""
        handles = []
        for task in tasks:
            self._count += 1
            self._waiting.append((self._count, task, budget_s, on_outcome, progress))
            handles.append(self._count)
        return handles

    def next(self) -> tuple[int, dict]:
        handle, task, budget_s, on_outcome, progress = self._waiting.popleft()
        deadline = None if budget_s is None else time.time() + budget_s
        return handle, run_pool_task(task, progress=progress, on_outcome=on_outcome, deadline=deadline)

    def close(self) -> None:
        self._waiting.clear()


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
    t_start, clock_start = time.perf_counter(), time.time()
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
                pending = [_resumed(j, store.manifest["failed"], spec.max_attempts) for j in plan
                           if not store.done(j.kind, j.id)]
                seqs = [j for j in pending if j.kind == "sequence"]
                if max_sequences is not None and len(seqs) > max_sequences:
                    keep = {j.id for j in seqs[:max_sequences]}
                    pending = [j for j in pending if j.kind != "sequence" or j.id in keep]
                report = StoreReport(path=loc.root, garment=garment.name, planned_sequences=seq_total,
                                     planned_fits=len(spec.shapes()), done_before=done_before, reconcile=rec)
                if executor is None:
                    executor = _make_executor(ray, spec)
                    executor_ready = time.time() - clock_start
                if ray is not None:
                    report.executor_ready = executor_ready
                driver = _Driver(spec, store, garment, body, executor, report, progress, say,
                                 getattr(executor, "device", None), clock_start)
                driver.run(pending, time_budget, t_start)
                report.pending = seq_total - len(store.manifest["sequences"])
                reports.append(report)
            finally:
                store.release()
    finally:
        if executor is not None:
            executor.close()
    return reports


def _resumed(job: Job, failed: dict, max_attempts: int) -> Job:
    """A pending job at the attempt after the one the manifest records as failed (an earlier run
    stopped before its retry ended; a job that failed its last attempt runs that attempt again)."""
    entry = failed.get(job.key)
    if entry is None:
        return job
    return replace(job, attempt=min(int(entry.get("attempts", 0)) + 1, max_attempts))


def _make_executor(ray: str | None, spec: DatasetSpec):
    if ray is None:
        return _LocalExecutor()
    from simgen.dataset.distributed import RayExecutor

    return RayExecutor(ray, spec)


def _seconds_left(time_budget: float | None, t_start: float) -> float | None:
    """[s] What is left of ``time_budget`` counted from ``t_start`` (a perf_counter value); None: no budget."""
    return None if time_budget is None else time_budget - (time.perf_counter() - t_start)


class _Driver:
    """Runs the pending jobs of one store in pools, round by round, and keeps the store's manifest
    and the run's report (:func:`generate_dataset` step 4)."""

    def __init__(self, spec, store, garment, body, executor, report, progress, say, device, clock_start) -> None:
        self.spec, self.store, self.garment, self.body = spec, store, garment, body
        self.executor, self.report, self.progress, self.say, self.device = executor, report, progress, say, device
        self.clock_start = clock_start   # time.time() at the run's start
        self.retry: list[Job] = []
        self.by_key: dict = {}
        self.submitted: dict = {}   # task name -> [s] from the run's start when it was handed to the executor
        self.failed_here: set = set()   # keys of the jobs that failed in this run (their retries may go beside)
        self._saved = time.perf_counter()
        self.total = 0       # cloth-frames planned (retries add theirs)
        self.done = 0        # cloth-frames simulated in the rounds that ended
        self.shown = 0

    def show(self, n: int) -> None:
        if self.progress is not None:
            self.shown = max(self.shown, min(n, self.total))
            self.progress(self.shown, self.total)

    def run(self, pending: list[Job], time_budget: float | None, t_start: float) -> None:
        try:
            self._rounds(pending, time_budget, t_start)
        finally:
            self.store.save_manifest()   # what was recorded since the last save, also on an error

    def _rounds(self, pending: list[Job], time_budget: float | None, t_start: float) -> None:
        """Keep every worker busy: the first jobs dealt into one pool per worker, and each retry in a
        pool of its own as soon as its failure is known: on a free worker, else beside a busy one
        where the executor has room (Ray on GPUs), not after the other pools."""
        spec, report = self.spec, self.report
        queue = list(pending)
        self.total = job_cloth_frames(spec, queue)
        self.show(0)
        t0 = time.perf_counter()
        running: dict = {}     # executor handle -> (round, task, started beside a busy worker)
        first, rounds, error = True, 0, None
        while queue or running:
            if report.stopped is None and error is None:
                rounds, first = self._launch(queue, running, rounds, first, time_budget, t_start)
            if not running:
                break
            handle, r = self.executor.next()
            if handle is None:
                # A running task reported failed jobs (Ray): their retries start now (_launch).
                self._requeue(queue, error)
                continue
            round_, task, beside = running.pop(handle)
            self._account(round_, task, r, beside)
            report.wall = time.perf_counter() - t0
            self.store.save_manifest()
            self.show(self.done)
            error = error or r["error"]
            if error is None and r["not_done"] and report.stopped is None:
                self._not_done(queue, r, time_budget, t_start)
            self._requeue(queue, error)
        if error:
            raise StoreWriteError(error)

    def _not_done(self, queue: list, r: dict, time_budget: float | None, t_start: float) -> None:
        """The jobs pool task ``r`` left undone: back into ``queue`` when the pool only refused them
        (a pool refuses a job by its own frame time, and a job refused by a full pool, such as a
        retry, often ends in time in a smaller one started after it) and budget is left; the new
        pool starts them as any first wave, before its frame time is known. A pool that dropped
        running jobs at its deadline, or a spent budget, stops the run there. Jobs the store already
        holds (a task that Ray ran again) are not queued again."""
        left = _seconds_left(time_budget, t_start)
        if r["abandoned_cloth_frames"] > 0 or (left is not None and left <= 0):
            self.report.stopped = f"time budget of {time_budget:g} s reached"
            return
        jobs = [j for j in r["not_done"] if not self.store.done(j.kind, j.id)]
        queue += jobs
        self.total += job_cloth_frames(self.spec, jobs)

    def _requeue(self, queue: list, error) -> None:
        """Move the retries that outcomes asked for into ``queue`` (dropped once the run stops:
        the manifest has their failures, so the next run starts them at their next attempt)."""
        if self.report.stopped is None and error is None:
            queue += self.retry
            self.total += job_cloth_frames(self.spec, self.retry)
        self.retry = []

    def _launch(self, queue, running, rounds, first, time_budget, t_start) -> tuple[int, bool]:
        """Start pools for what ``queue`` holds (:func:`_next_jobs`): on the free workers, else
        (retries of jobs that failed in this run, not jobs resumed at a later attempt) beside a busy
        one while the executor has room (``beside``); returns the rounds launched so far and whether
        the first is still to come."""
        free = self.executor.parallel - sum(not b for _, _, b in running.values())
        room = self.executor.beside - sum(b for _, _, b in running.values())
        while queue and (free > 0 or (room > 0 and not first)):
            left = _seconds_left(time_budget, t_start)
            if left is not None and left <= 0:
                self.report.stopped = f"time budget of {time_budget:g} s reached"
                break
            template_running = any(j.kind == "template" for _, t, _ in running.values() for j in t.jobs)
            jobs = _next_jobs(queue, first, template_running)
            if not jobs:
                break
            beside = free <= 0
            if beside and not all(j.key in self.failed_here for j in jobs):
                queue += jobs     # beside a busy pool only retries of failures of this run
                break
            first, rounds = False, rounds + 1
            self.by_key.update({j.key: j for j in jobs})
            loc = self.store.loc.root if self.store.loc.is_local else self.store.loc.url()
            parts = _split(jobs, 1 if beside else free)
            tasks = [BatchTask(location=loc, spec=self.spec, garment=self.garment.name, jobs=part,
                               attempt=jobs[0].attempt, device=self.device, body_hash=self.body.hash,
                               name=f"{self.garment.name}/{rounds}.{i}") for i, part in enumerate(parts)]
            submitted = time.time() - self.clock_start
            handles = self.executor.start(tasks, left, self.record, lambda n: self.show(self.done + n), beside=beside)
            running.update({h: (rounds, t, beside) for h, t in zip(handles, tasks)})
            self.submitted.update({t.name: submitted for t in tasks})
            if beside:
                room -= len(tasks)
            else:
                free -= len(tasks)
        return rounds, first

    def _account(self, round_: int, task: BatchTask, r: dict, beside: bool) -> None:
        """Add one ended task to the report and the cloth-frame totals."""
        report = self.report
        report.tasks.append(self._task_entry(round_, task, r, beside))
        report.slots = max(report.slots, r["slots"])
        self.done += r["cloth_frames"]
        report.cloth_frames += r["cloth_frames"]
        report.simulate_wall += r["wall"]
        report.step_wall += r["step_s"]
        report.write_wall += r["write_s"]
        report.write_wait += r["write_wait"]
        if task.attempt > 1:
            report.retry_cloth_frames += r["cloth_frames"]
            report.retry_simulate_wall += r["wall"]
        else:
            report.retry_cloth_frames += r["retry_cloth_frames"]
            report.retry_simulate_wall += r["retry_wall"]
        self.total -= job_cloth_frames(self.spec, r["not_done"]) - r["abandoned_cloth_frames"]

    def _task_entry(self, round_: int, task: BatchTask, r: dict, beside: bool) -> dict:
        since = {k: v - self.clock_start for k, v in r["clock"].items()}
        return {"round": round_, "worker": r.get("worker"), "beside": beside,
                "submitted": self.submitted.get(task.name), **since, "cloth_frames": r["cloth_frames"],
                "retry_cloth_frames": r["retry_cloth_frames"], "retry_wall": r["retry_wall"],
                "slots": r["slots"], "gpu_memory_high_bytes": r["gpu_memory_high_bytes"],
                **({"drain": r["drain"]} if "drain" in r else {}),
                "timeline": [[round(t + since["start"], 2), *rest] for t, *rest in r.get("timeline", [])]}

    def record(self, o: dict) -> None:
        """Enter one outcome into the manifest and the report; a failed job with attempts left runs
        again with the substep halved: in its own pool (``retry: "pool"``), else in a later round."""
        spec, report, store = self.spec, self.report, self.store
        job = self.by_key[f"{o['kind']}:{o['id']}"]
        if o.get("waiting"):
            # Not simulated for its own sake (the template failed in its pool): again, same attempt,
            # unless the template has failed for good.
            if "template:template" in report.failed:
                report.failed[job.key] = "the template relaxation failed"
                store.record({"ok": False, "kind": job.kind, "id": job.id, "attempt": job.attempt,
                              "message": "the template relaxation failed"})
            else:
                self.retry.append(job)
            return
        store.record(o)
        if o["ok"]:
            report.failed.pop(job.key, None)
            if o["kind"] == "sequence" and not o.get("reused"):
                report.written += 1
        elif job.attempt < spec.max_attempts:
            self.say(f"{job.key} failed on attempt {job.attempt} ({o['message']}); retrying with "
                     f"{spec.substeps * 2 ** job.attempt} substeps")
            again = Job(**{**job.__dict__, "attempt": job.attempt + 1})
            if o.get("retry") == "pool":
                self.by_key[again.key] = again
                self.total += job_cloth_frames(spec, [again])
            else:
                self.retry.append(again)
                self.failed_here.add(again.key)
            report.retried += 1
            report.failed_attempts.append({"job": job.key, "attempt": job.attempt, "message": o["message"],
                                           "at": time.time() - self.clock_start})
        else:
            report.failed[job.key] = o["message"]
        # Rewritten every few seconds, not after every job (a large manifest on an object store
        # costs the pool's time); each round ends with a save, and a kill in between is what
        # reconcile() repairs on the next run (committed nodes are adopted).
        if time.perf_counter() - self._saved > MANIFEST_EVERY_S:
            store.save_manifest()
            self._saved = time.perf_counter()
