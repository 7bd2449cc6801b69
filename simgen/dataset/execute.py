"""Jobs, batches and the function that simulates one batch and writes its nodes.

The plan of a store is a list of :class:`Job`: one ``template`` job (the garment relaxed on the
template body: betas 0, a one-frame rest-pose clip), one ``fit`` job per shape (same clip, betas
of the shape: relax, ramp the shape from 0, rest -> S_c(beta, 0)) and one ``sequence`` job per
(motion, shape) (relax, ramp shape and pose to the clip's first frame, rest, animate). Every job
runs simulate()'s start protocol from the garment template, so the relaxation of the thesis
("relax once, start every simulation from it") is re-run inside each job: it is deterministic
and the same for all jobs (the body is the template body at rest throughout), and simulate()
takes no initial state.

:func:`run_batch` runs in the driver (local execution) or in a Ray task: it simulates the jobs
of one batch in one batched solver call (:func:`simgen.sim.simulate_batch`), then writes each
finished job as a committed node. The two phases are :func:`simulate_batch_task` (device work, on the thread that owns Warp) and :func:`write_batch`
(host work: ground truth, statistics, Zarr, commits); the local executor runs the write of one
batch in a background thread while the next batch simulates (:mod:`simgen.dataset.generate`).
Clips of unequal length share a batch: the batch runs to the longest clip and each result is cut
to its own frames (simulate_batch's contract), so the planner groups clips of similar length. An instance
that diverges comes back as a failure in its slot while the others are written; the driver puts
it into a later batch with the substep halved (attempt k runs substeps * 2^(k-1)) until
``execution.max_attempts``. A sequence with a strain outlier (a triangle past the check's limit
on some frame) is such a failure too while attempts are left (:func:`_strain_outlier`).
"""

from __future__ import annotations

import functools
import time
from dataclasses import dataclass, field, replace

import numpy as np

from simgen._warp_log import quiet_warp
from simgen.dataset.storage import Location, StoreWriteError
from simgen.errors import InputError

__all__ = ["Job", "BatchTask", "SimulatedBatch", "run_batch", "simulate_batch_task", "write_batch", "rest_clip",
           "simulate_jobs", "job_cloth_frames"]


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
    """What a batch needs, picklable for Ray: store location, spec, garment name, jobs, attempt."""

    location: str
    spec: object
    garment: str
    jobs: list
    attempt: int = 1
    device: str | None = None
    body_hash: str | None = None
    meta: dict = field(default_factory=dict)

    @property
    def substeps_factor(self) -> int:
        return 2 ** (self.attempt - 1)


def rest_clip(fps: float, name: str = "rest"):
    """A one-frame clip in the rest pose (zero rotations, zero translation)."""
    from simgen.motion.clip import MotionClip

    return MotionClip(name, fps, np.zeros((1, 24, 3)), np.zeros((1, 3)), {"source": "simgen.dataset rest pose"})


def job_cloth_frames(spec, jobs) -> int:
    """Cloth-frames a batch simulates: (protocol + clip frames) per job; frame 0 of a clip takes no step."""
    return sum(spec.protocol_frames() + j.frames - 1 for j in jobs)


@functools.lru_cache(maxsize=4)
def _load_body(source: str):
    from simgen import body as body_pkg

    return body_pkg.load(source)


@functools.lru_cache(maxsize=8)
def _load_garment(name: str, body_source: str):
    from simgen.garment.library import load_garment

    return load_garment(name, body=_load_body(body_source))


def simulate_jobs(garment, body, jobs: list[Job], config, progress=None) -> list:
    """Simulate jobs as one batch (:func:`simgen.sim.simulate_batch`, all instances in one system):
    a :class:`simgen.sim.SimulationResult` or :class:`simgen.sim.SimulationFailure` per job, in order.

    progress(cloth_frames_done) is called after every batch frame.
    """
    from simgen.sim import SimulationJob, simulate_batch

    quiet_warp()
    n = len(jobs)

    def on_batch(done, total_frames, phase):
        if progress is not None:
            progress(done * n)

    return simulate_batch(garment, body, [SimulationJob(j.clip, betas=j.betas, key=j.key) for j in jobs], config,
                          progress=on_batch)


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


def _strain_outlier(spec, job: Job, per_frame: dict) -> str | None:
    """Why a simulated sequence is to be simulated again, or None.

    A sequence with a frame where one triangle is stretched past the limit of ``simgen dataset
    check`` is a failed attempt while attempts are left (``execution.retry_strain_outliers``): such
    spikes come from a vertex the step left deep inside a fast limb, and a smaller substep makes
    that intrusion smaller. The last attempt is written whatever its strain (the check reports
    it). Outliers at body self-intersections, which the check counts apart, are retried too: telling
    them apart needs the body re-posed, a device job this host-side phase leaves to the check.
    """
    from simgen.dataset.quality import DEFAULT_MAX_STRAIN

    if job.kind != "sequence" or not spec.retry_strain_outliers or job.attempt >= spec.max_attempts:
        return None
    strain = np.asarray(per_frame.get("strain_max", ()))
    if strain.size == 0 or not strain.max() > DEFAULT_MAX_STRAIN:
        return None
    k = int(np.argmax(strain))
    return (f"strain outlier: a triangle stretched {100 * strain[k]:.0f}% at frame {k} (the check's limit is "
            f"{100 * DEFAULT_MAX_STRAIN:g}%; {int(np.sum(strain > DEFAULT_MAX_STRAIN))} frames over it)")


def _rest_frames(result) -> np.ndarray:
    phases = np.asarray(result.protocol_phases)
    return np.asarray(result.protocol_positions)[phases == "rest"].astype(np.float32)


@dataclass
class SimulatedBatch:
    """A batch between its two phases: simulated (host arrays), not written yet.

    What :func:`write_batch` needs and nothing on the device: the task, the spec with its device
    resolved, the solver config, garment and body (host objects), the jobs simulated (template
    first), their results (SimulationResult or SimulationFailure), the outcomes of jobs whose node was
    already committed, and the phase's timings (wall, step_s) and cloth-frames.
    """

    task: BatchTask
    spec: object
    config: object
    garment: object
    body: object
    todo: list
    results: list
    reused: list
    wall: float
    step_s: float
    cloth_frames: int


def _outcome_base(job: Job) -> dict:
    return {"kind": job.kind, "id": job.id, "attempt": job.attempt, "frames": job.frames, "motion": job.motion,
            "shape_id": job.shape_id, "split": job.split}


def run_batch(task: BatchTask, progress=None) -> dict:
    """Simulate one batch and write its nodes; returns {outcomes, error, wall, cloth_frames, step_s, write_s}.

    The two phases in sequence: :func:`simulate_batch_task`, then :func:`write_batch` (the local
    executor may run the second in a background thread while the next batch simulates; Ray tasks
    call this). wall [s]: the batch's simulation (``simulate_jobs``); step_s [s]: the solver's
    stepping within it (the per-frame step times of the batch's longest job, protocol included; the
    rest of ``wall`` is posing, statistics and host copies); write_s [s]: ground truth, statistics
    and store writes.

    Jobs whose node is already committed (an earlier attempt of this task) are not simulated again.
    Each outcome: ok, kind, id, attempt, checksum (ok) or message (failed), frames, motion,
    shape_id, split. A write failure stops the batch: the outcomes so far are returned with
    ``error`` set to one sentence (the store stays consistent; what was committed is kept).
    """
    return write_batch(simulate_batch_task(task, progress=progress))


def simulate_batch_task(task: BatchTask, progress=None) -> SimulatedBatch:
    """The simulation phase of :func:`run_batch`: runs on the thread that owns the device (Warp).

    Raises what the simulation raises (and the testing hook's injected fault); writes nothing.
    """
    from simgen.sim import SimulationFailure

    _injected_fault()
    spec = task.spec
    loc = Location(task.location)
    body = _load_body(spec.body)
    if task.body_hash is not None and body.hash != task.body_hash:
        raise InputError(f"body model {spec.body} changed since the store was created (hash mismatch)")
    garment = _load_garment(task.garment, spec.body)
    if task.device is not None:
        spec = replace(spec, device=task.device)
    config = spec.solver_config(substeps_factor=task.substeps_factor)
    reused: list[dict] = []
    todo = []
    for job in task.jobs:
        commit = loc.committed(_node_rel(job))
        if commit is not None:
            reused.append({**_outcome_base(job), "ok": True, "checksum": commit["checksum"], "reused": True})
        else:
            todo.append(job)
    # Template first: the fits of the same batch need its smoothed version.
    todo.sort(key=lambda j: {"template": 0, "fit": 1, "sequence": 2}[j.kind])
    t0 = time.perf_counter()
    results = simulate_jobs(garment, body, todo, config, progress=progress) if todo else []
    wall = time.perf_counter() - t0
    step_s = max((float(np.sum(r.stats["step_time"])) + float(np.sum(r.protocol_stats.get("step_time", 0.0)))
                  for r in results if not isinstance(r, SimulationFailure) and "step_time" in r.stats), default=0.0)
    return SimulatedBatch(task=task, spec=spec, config=config, garment=garment, body=body, todo=todo,
                          results=results, reused=reused, wall=wall, step_s=step_s,
                          cloth_frames=job_cloth_frames(spec, todo))


def write_batch(simulated: SimulatedBatch) -> dict:
    """The write phase of :func:`run_batch`: ground truth, statistics and one committed node per job.

    Host work only (numpy, Zarr, the store), so it may run in a thread other than the simulation's.
    Returns :func:`run_batch`'s dict; a :class:`StoreWriteError` ends the batch with ``error`` set.
    """
    from simgen.dataset.groundtruth import fit_displacement, smooth_garment
    from simgen.dataset.quality import triangle_rest_inverse
    from simgen.sim import SimulationFailure

    t_write = time.perf_counter()
    sb = simulated
    spec, config, garment, body, wall = sb.spec, sb.config, sb.garment, sb.body, sb.wall
    todo, results, cloth_frames = sb.todo, sb.results, sb.cloth_frames
    loc = Location(sb.task.location)
    base = _outcome_base
    outcomes: list[dict] = list(sb.reused)
    rest_inv = triangle_rest_inverse(garment.vertices, garment.faces)
    smoothing = spec.smoothing_params()
    faces = np.asarray(garment.faces)
    template_smoothed = None
    error = None
    for job, res in zip(todo, results):
        msg = None
        if isinstance(res, SimulationFailure):
            msg = f"{res.message} (phase {res.phase}, frame {res.frame})"
        elif res.positions.shape[0] != job.frames:
            msg = f"the solver returned {res.positions.shape[0]} frames for a clip of {job.frames}"
        elif not np.all(np.isfinite(res.positions)):
            msg = "non-finite positions (NaN or inf) in the result"
        if msg is not None:
            outcomes.append({**base(job), "ok": False, "message": msg})
            continue
        per_frame, summary = _frame_stats(res, faces, rest_inv)
        outlier = _strain_outlier(spec, job, per_frame)
        if outlier is not None:
            outcomes.append({**base(job), "ok": False, "message": outlier})
            continue
        share = wall * (spec.protocol_frames() + job.frames - 1) / max(cloth_frames, 1)
        summary.update(wall_time=share, batch_wall_time=wall, batch_size=len(todo), attempts=job.attempt,
                       substeps=config.substeps, device=str(config.device))
        try:
            if job.kind == "template":
                relaxed = res.positions[0].astype(np.float64)
                # Rounded to the stored float32 so fits of this batch and of later ones subtract the same T_c.
                template_smoothed = smooth_garment(relaxed, faces, smoothing).astype(np.float32).astype(np.float64)
                arrays = {"vertices": relaxed.astype(np.float32), "smoothed": template_smoothed.astype(np.float32),
                          "faces": faces.astype(np.int32),
                          "skin_weights": np.asarray(garment.skin_weights, dtype=np.float32),
                          "garment_template": np.asarray(garment.vertices, dtype=np.float32)}
                attrs = {"smoothing": smoothing.to_dict(), "stats": summary, "garment": garment.name,
                         "protocol_frames": spec.protocol_frames()}
            elif job.kind == "fit":
                if template_smoothed is None:
                    template_smoothed = _stored_template_smoothed(loc)
                if template_smoothed is None:
                    outcomes.append({**base(job), "ok": False, "waiting": True,
                                     "message": "the template relaxation is not in the store yet"})
                    continue
                fit_v = res.positions[0].astype(np.float64)
                arrays = {"betas": _full_betas(job.betas, body).astype(np.float32),
                          "vertices": fit_v.astype(np.float32),
                          "fit_displacement": fit_displacement(fit_v, template_smoothed, faces, smoothing
                                                               ).astype(np.float32)}
                if spec.store_rest_frames:
                    arrays["rest_vertices"] = _rest_frames(res)
                attrs = {"shape_id": job.shape_id, "betas": _full_betas(job.betas, body).tolist(), "stats": summary}
            else:
                T = job.frames
                clip = job.clip
                betas = np.repeat(_full_betas(job.betas, body)[None], T, 0).astype(np.float32)
                arrays = {"garment_vertices": res.positions.astype(np.float32),
                          "poses": clip.poses.astype(np.float32), "trans": clip.trans.astype(np.float32),
                          "betas": betas}
                if spec.store_rest_frames:
                    arrays["rest_garment_vertices"] = _rest_frames(res)
                for k, v in per_frame.items():
                    arrays[f"stats/{k}"] = np.asarray(v)
                attrs = {"motion": job.motion, "motion_source": job.motion_source, "fps": float(spec.fps),
                         "split": job.split, "shape_id": job.shape_id, "betas": _full_betas(job.betas, body).tolist(),
                         "frames": T, "start_frame": spec.start_frame, "stats": summary,
                         "retries": summary["solver_retries"], "wall_time": summary["wall_time"]}
            chunks = {"garment_vertices": (spec.chunk_frames,) + res.positions.shape[1:],
                      "rest_garment_vertices": (spec.chunk_frames,) + res.positions.shape[1:]}
            commit = loc.write_node(_node_rel(job), arrays, attrs, chunks=chunks)
        except StoreWriteError as exc:
            error = str(exc)
            break
        outcomes.append({**base(job), "ok": True, "checksum": commit["checksum"]})
    return {"outcomes": outcomes, "error": error, "wall": wall, "cloth_frames": cloth_frames, "step_s": sb.step_s,
            "write_s": time.perf_counter() - t_write}


def _injected_fault() -> None:
    # Testing hook for task retries: with SIMGEN_DATASET_FAULT_ONCE=FILE the first batch to find FILE
    # missing creates it and fails, as a worker that crashed would.
    import os

    marker = os.environ.get("SIMGEN_DATASET_FAULT_ONCE")
    if marker:
        try:
            with open(marker, "x"):
                pass
        except FileExistsError:
            return
        raise RuntimeError("injected fault (SIMGEN_DATASET_FAULT_ONCE)")


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
