"""The results of a batched simulation: :class:`SimulationResult` (positions, statistics and
metadata of one job), :class:`SimulationFailure` (the slot of a job that diverged), and the
:class:`Recorder` that collects them frame by frame.
"""

from __future__ import annotations

import json
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from simgen.sim.frame_stats import FRAME_STAT_KEYS, stack_stats
from simgen.sim.batch import BatchSetup

__all__ = ["SimulationResult", "SimulationFailure", "Recorder"]


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


class Recorder:
    """Collects every live instance's cloth positions and statistics frame by frame, and makes the
    results.

    Protocol frames go to ``protocol_positions`` / ``protocol_stats``, animation frames below each
    job's own frame count to ``positions`` / ``stats`` (and the posed body with
    ``config.record_body``).
    """

    def __init__(self, setup: BatchSetup) -> None:
        N = setup.num_instances
        self.setup = setup
        self._positions = [[] for _ in range(N)]
        self._stats = [[] for _ in range(N)]
        self._body = [[] for _ in range(N)]
        self._proto_positions = [[] for _ in range(N)]
        self._proto_stats = [[] for _ in range(N)]
        self._proto_phases: list[str] = []
        self._t_start = time.perf_counter()
        self._frames = 0

    def record(self, phase: str, k: int, failures: dict, betas: np.ndarray, step_time: float,
               t_frame: float) -> None:
        """Measure and keep frame (phase, k) of every instance not in ``failures``.

        betas (N, nb): each instance's body shape now; step_time [s]: the frame's stepping (0 if it
        took no step); t_frame [s]: ``time.perf_counter()`` at the frame's start.
        """
        s = self.setup
        rows = s.stats.measure(s.state.positions, betas)
        st, per = s.solver.stats, s.solver.instance_stats
        x = s.state.positions.numpy().astype(np.float32)
        wall = time.perf_counter() - t_frame
        body_now = s.wbody.vertices.numpy() if s.config.record_body and phase == "animate" else None
        starts = np.asarray(s.model.vertex_start)
        for i in range(s.num_instances):
            if i in failures:
                continue
            row = rows[i]
            row.update(depth_before_projection=float(per["max_penetration"][i]), retries=int(per["retries"][i]),
                       unresolved=int(per["unresolved"][i]), newton_iterations=st["newton_iterations"],
                       cg_iterations=st["cg_iterations"], step_time=step_time, wall_time=wall)
            xi = x[starts[i]:starts[i + 1]]
            if phase != "animate":
                self._proto_positions[i].append(xi)
                self._proto_stats[i].append(row)
            elif k < s.num_out[i]:
                self._positions[i].append(xi)
                self._stats[i].append(row)
                if body_now is not None:
                    self._body[i].append(body_now[i].astype(np.float32))
        if phase != "animate":
            self._proto_phases.append(phase)
        self._frames += 1

    def results(self, failures: dict) -> list:
        """One :class:`SimulationResult` per job, or its :class:`SimulationFailure` (failures:
        instance -> (phase, frame, message), :attr:`FrameRunner.failures`), in job order."""
        s = self.setup
        wall_total = time.perf_counter() - self._t_start
        body_faces = s.wbody.faces.numpy().reshape(-1, 3).astype(np.int32)
        out: list = []
        for i in range(s.num_instances):
            if i in failures:
                phase, k, message = failures[i]
                out.append(SimulationFailure(s.keys[i], message, phase, k))
            else:
                out.append(self._result(i, wall_total, body_faces))
        return out

    def _result(self, i: int, wall_total: float, body_faces: np.ndarray) -> SimulationResult:
        s, cfg = self.setup, self.setup.config
        garment, nv = s.garment, s.garment.num_vertices
        stats = stack_stats(self._stats[i])
        proto = self._proto_stats[i]
        metadata = dict(
            key=s.keys[i], garment=garment.name, garment_vertices=int(nv), garment_triangles=int(len(garment.faces)),
            body=s.body.name, body_vertices=int(s.body.num_vertices), motion=s.clips[i].name,
            motion_fps=float(s.clips[i].fps), fps=s.fps, substeps=s.substeps, dt=s.dt, frames=s.num_out[i],
            betas=[float(b) for b in s.target_betas[i]], material=asdict(s.materials[i]),
            config=dict(relax_frames=cfg.relax_frames, ramp_frames=cfg.ramp_frames, rest_frames=cfg.rest_frames,
                        device=str(s.device), cuda_graph=s.use_graph),
            solver=json.loads(json.dumps(asdict(cfg.solver), default=float)),
            batch_size=s.num_instances,
            initial_inside=int(s.initial[i]["inside_count"]),
            wall_time=wall_total,
            wall_time_per_frame=wall_total / self._frames,
            max_depth_regular=float(stats["max_depth_regular"].max()),
            max_self_intersection_count=int(stats["self_intersection_count"].max()),
            retries=int(stats["retries"].sum() + sum(r["retries"] for r in proto)),
        )
        return SimulationResult(
            positions=np.stack(self._positions[i]),
            faces=np.asarray(garment.faces, dtype=np.int32),
            fps=s.fps, dt=s.dt, stats=stats,
            protocol_positions=(np.stack(self._proto_positions[i]) if self._proto_positions[i]
                                else np.zeros((0, nv, 3), np.float32)),
            protocol_phases=np.array(self._proto_phases, dtype=str),
            protocol_stats=stack_stats(proto) if proto else {key: np.zeros(0) for key in FRAME_STAT_KEYS},
            body_vertices=np.stack(self._body[i]) if cfg.record_body else None,
            body_faces=body_faces,
            metadata=metadata,
        )
