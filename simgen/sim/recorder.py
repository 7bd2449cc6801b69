"""The results of a batched simulation: :class:`SimulationResult` (positions, statistics and
metadata of one job), :class:`SimulationFailure` (a job that diverged), :func:`measure_frame` (the
statistics of every slot at a frame's end) and the :class:`JobRecorder` that collects one job's
frames.
"""

from __future__ import annotations

import json
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from simgen.sim.frame_stats import FRAME_STAT_KEYS, stack_stats
from simgen.sim.batch import BatchSetup

__all__ = ["SimulationResult", "SimulationFailure", "JobRecorder", "measure_frame"]


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


@dataclass
class SimulationFailure:
    """The slot of a :func:`simulate_batch` instance that diverged: its key, the reason, and where
    (``phase`` of the start protocol or "animate", ``frame`` index within that phase)."""

    key: str
    message: str
    phase: str
    frame: int


def measure_frame(setup: BatchSetup, betas: np.ndarray, step_time: float, t_frame: float, slots=None) -> tuple:
    """Measure the slots at the end of a frame.

    betas (N, nb): each slot's body shape now; step_time [s]: the frame's stepping; t_frame [s]:
    ``time.perf_counter()`` at the frame's start; slots: those to measure (None: all). Returns
    (rows, positions, body): one dict of :data:`FRAME_STAT_KEYS` per slot (None for a slot not
    measured), the cloth [m] (N*V, 3) float32, and the posed body [m] (N, Vb, 3) with
    ``config.record_body`` (else None).
    """
    s = setup
    x = s.state.positions.numpy()   # a fresh host copy from a GPU; on the CPU a view of the state
    x = np.array(x, dtype=np.float32) if s.state.positions.device.is_cpu else np.asarray(x, dtype=np.float32)
    rows = s.stats.measure(s.state.positions, betas, slots, host_positions=x)
    st, per = s.solver.stats, s.solver.instance_stats
    wall = time.perf_counter() - t_frame
    for i, row in enumerate(rows):
        if row is None:
            continue
        row.update(depth_before_projection=float(per["max_penetration"][i]), retries=int(per["retries"][i]),
                   unresolved=int(per["unresolved"][i]), newton_iterations=st["newton_iterations"],
                   cg_iterations=st["cg_iterations"], step_time=step_time, wall_time=wall)
    body = s.wbody.vertices.numpy() if s.config.record_body else None
    return rows, x, body


def _merged_solver_stats(a: dict | None, b: dict) -> dict:
    """The solver's entries of two batch frames' rows as one frame's: counts and times summed, the
    depth before projection the deeper (``a`` None: ``b``'s)."""
    keys = ("retries", "unresolved", "newton_iterations", "cg_iterations", "step_time", "wall_time")
    if a is None:
        return {k: b[k] for k in keys + ("depth_before_projection",)}
    return {**{k: a[k] + b[k] for k in keys},
            "depth_before_projection": max(a["depth_before_projection"], b["depth_before_projection"])}


#: The solver's entries of a frame row that took no step (a clip's frame 0: the rest phase's end).
_NO_STEP = dict(depth_before_projection=0.0, retries=0, unresolved=0, newton_iterations=0, cg_iterations=0,
                step_time=0.0)


class JobRecorder:
    """Collects one job's cloth positions and statistics frame by frame, and makes its result.

    Protocol frames go to ``protocol_positions`` / ``protocol_stats``, animation frames to
    ``positions`` / ``stats`` (and the posed body with ``config.record_body``).

    setup: the :class:`BatchSetup`; key: the job's label; clip: its MotionClip; num_out: its
    output frames; betas (B',): its target shape; material: its Material; substeps_factor: the job
    runs at that many times the batch's substeps, each of its frames in that many batch frames
    (:meth:`hold` the rows of all but the last).
    """

    def __init__(self, setup: BatchSetup, key: str, clip, num_out: int, betas: np.ndarray, material,
                 substeps_factor: int = 1) -> None:
        self.setup, self.key, self.clip, self.num_out = setup, key, clip, int(num_out)
        self.betas, self.material = betas, material
        self.factor = int(substeps_factor)
        self._held: dict | None = None
        self._positions: list = []
        self._stats: list = []
        self._body: list = []
        self._proto_positions: list = []
        self._proto_stats: list = []
        self._proto_phases: list[str] = []
        self._t_start = time.perf_counter()
        self.share = 0.0   # [s] this job's share of the batch's wall time (each frame's over its active slots)

    def hold(self, row: dict) -> None:
        """Keep the solver's statistics of a batch frame that stepped part of the job's coming frame:
        :meth:`record` adds them to that frame's (sums; the deepest depth before projection)."""
        self._held = _merged_solver_stats(self._held, row)

    def record(self, phase: str, k: int, row: dict, positions: np.ndarray, body: np.ndarray | None) -> None:
        """Keep frame (phase, k): its row of statistics, cloth [m] (V, 3) and posed body [m] (Vb, 3) or None;
        :meth:`record_start` for a clip's frame 0."""
        if self._held is not None:
            row, self._held = {**row, **_merged_solver_stats(self._held, row)}, None
        if phase != "animate":
            self._proto_positions.append(positions)
            self._proto_stats.append(row)
            self._proto_phases.append(phase)
        else:
            self._positions.append(positions)
            self._stats.append(row)
            if body is not None and self.setup.config.record_body:
                self._body.append(body.astype(np.float32))

    def record_start(self, row: dict, positions: np.ndarray, body: np.ndarray | None) -> None:
        """Keep the clip's frame 0, the rest phase's end state (``row`` measured there; it took no step)."""
        self.record("animate", 0, {**row, **_NO_STEP}, positions, body)

    def failure(self, phase: str, k: int, message: str) -> SimulationFailure:
        return SimulationFailure(self.key, message, phase, k)

    def result(self) -> SimulationResult:
        """The job's :class:`SimulationResult` (all of its frames recorded)."""
        s, cfg = self.setup, self.setup.config
        garment, nv = s.garment, s.garment.num_vertices
        wall_total = time.perf_counter() - self._t_start
        frames = len(self._stats) + len(self._proto_stats)
        stats = stack_stats(self._stats)
        proto = self._proto_stats
        metadata = dict(
            key=self.key, garment=garment.name, garment_vertices=int(nv), garment_triangles=int(len(garment.faces)),
            body=s.body.name, body_vertices=int(s.body.num_vertices), motion=self.clip.name,
            motion_fps=float(self.clip.fps), fps=s.fps, substeps=s.substeps * self.factor, dt=s.dt / self.factor,
            frames=self.num_out,
            betas=[float(b) for b in self.betas], material=asdict(self.material),
            config=dict(relax_frames=cfg.relax_frames, ramp_frames=cfg.ramp_frames, rest_frames=cfg.rest_frames,
                        device=str(s.device), cuda_graph=s.use_graph),
            solver=json.loads(json.dumps(asdict(cfg.solver), default=float)),
            batch_size=s.num_instances,
            initial_inside=int(s.initial_inside),
            wall_time=wall_total,
            wall_time_per_frame=wall_total / max(frames, 1),
            wall_share=self.share,
            max_depth_regular=float(stats["max_depth_regular"].max()),
            max_self_intersection_count=int(stats["self_intersection_count"].max()),
            retries=int(stats["retries"].sum() + sum(r["retries"] for r in proto)),
        )
        return SimulationResult(
            positions=np.stack(self._positions),
            faces=np.asarray(garment.faces, dtype=np.int32),
            fps=s.fps, dt=s.dt / self.factor, stats=stats,
            protocol_positions=(np.stack(self._proto_positions) if self._proto_positions
                                else np.zeros((0, nv, 3), np.float32)),
            protocol_phases=np.array(self._proto_phases, dtype=str),
            protocol_stats=stack_stats(proto) if proto else {key: np.zeros(0) for key in FRAME_STAT_KEYS},
            body_vertices=np.stack(self._body) if cfg.record_body else None,
            body_faces=s.wbody.faces.numpy().reshape(-1, 3).astype(np.int32),
            metadata=metadata,
        )
