"""What idle slots cost a simulation pool: frame time of a pool of N slots with K of them busy.

A :class:`simgen.sim.SimulationPool` of ``--slots`` N (the dataset preset's solver settings, its
garment and body) runs K jobs of ``--motion`` at once (K from ``--busy``), the others idle (pinned,
no body). The protocol is cut to 1 + 2 + 1 frames so that the timed frames are animated ones; the
first ``--warmup`` frames (kernel loads, graph captures) are not timed. Per K: the median wall time
of a pool frame (stepping, statistics, host copies) and of its stepping alone, and that per busy
slot. If idle slots cost the kernels nothing, the frame time falls with K; if they cost as much as
busy ones, it stays flat.

    python scripts/bench_pool_occupancy.py --device cuda:0 --slots 128 --busy 128 32 8 1 --out occ.json

With ``--parts`` the timed frames run again with the device synchronised around each part of a
frame (the solver's stepping, the frame statistics and their pieces, host copies, recording, the
next frame's targets), each part's own time (its inner parts taken out) averaged per frame under
its path ("frame/statistics/measure/crossings"); "frame" is what the step spent outside every part. The
synchronisation removes any overlap of host and device work, so the parts add up to the synced
frame, which may be longer than the unsynced one reported beside it.

Prints (and writes with --out) JSON with the device, commit and sizes.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from dataset_bench import _commit, _device, _emit  # noqa: E402  (scripts/ sibling: records and output)


_INHERITED = object()   # marks an attribute that the patched class did not define itself


class _PartTimer:
    """Times the parts of a pool frame: each patched callable synchronises the device before and
    after it and adds its own time [s] (its inner parts' taken out) under its path."""

    def __init__(self, device) -> None:
        self.device, self.own, self._stack, self._undo = device, {}, [], []

    def _sync(self) -> None:
        import warp as wp

        if not self.device.is_capturing:   # a part called inside a graph capture is not synchronised
            wp.synchronize_device(self.device)

    def patch(self, owner, attr: str, label: str) -> None:
        inner = getattr(owner, attr)
        timer = self

        def timed(*args, **kwargs):
            timer._sync()
            path = "/".join([f[0] for f in timer._stack] + [label])
            timer._stack.append([label, 0.0])
            t0 = time.perf_counter()
            try:
                return inner(*args, **kwargs)
            finally:
                timer._sync()
                total = time.perf_counter() - t0
                _, children = timer._stack.pop()
                timer.own[path] = timer.own.get(path, 0.0) + total - children
                if timer._stack:
                    timer._stack[-1][1] += total

        self._undo.append((owner, attr, owner.__dict__.get(attr, _INHERITED)))
        setattr(owner, attr, timed)

    def restore(self) -> None:
        for owner, attr, original in reversed(self._undo):
            if original is _INHERITED:
                delattr(owner, attr)
            else:
                setattr(owner, attr, original)
        self._undo.clear()


def _frame_parts(pool, frames: int) -> dict:
    """Mean own time [ms] per frame of each part of ``frames`` more pool frames (module doc)."""
    import warp as wp

    import simgen.sim.placement as placement
    import simgen.sim.pool as pool_module
    from simgen.garment.crossings import CrossingCounter
    from simgen.sim.frame_stats import FrameStats
    from simgen.sim.recorder import JobRecorder

    timer = _PartTimer(pool.setup.state.positions.device)
    patched = ((type(pool), "step", "frame"), (type(pool), "fill", "fill"),
               (type(pool), "_frame_targets", "targets"), (type(pool.runner), "run", "stepping"),
               (pool_module, "measure_frame", "statistics"), (FrameStats, "measure", "measure"),
               (CrossingCounter, "count_points", "crossings"), (FrameStats, "_strain_max", "strain"),
               (placement, "placement_rows", "placement"), (wp.Mesh, "refit", "bvh_refit"),
               (wp.array, "numpy", "host_copy"), (JobRecorder, "record", "record"))
    try:
        for owner, attr, label in patched:
            timer.patch(owner, attr, label)
        t0 = time.perf_counter()
        for _ in range(frames):
            pool.step()
        synced = time.perf_counter() - t0
    finally:
        timer.restore()
    parts = {path: 1e3 * t / frames for path, t in sorted(timer.own.items(), key=lambda kv: -kv[1])}
    return {"synced_frame_ms": 1e3 * synced / frames, "parts_ms": parts}


def _time_pool(garment, body, cfg, fps: float, slots: int, busy: int, motion: str, warmup: int, frames: int,
               parts: bool) -> dict:
    from simgen.sim import SimulationJob, SimulationPool

    pool = SimulationPool(garment, body, slots, cfg, fps=fps)
    for k in range(busy):
        pool.submit(SimulationJob(motion, frames=warmup + (2 if parts else 1) * frames + 2, key=f"job{k}"))
    walls, steps = [], []
    for i in range(warmup + frames):
        t0 = time.perf_counter()
        before = pool.step_time
        pool.step()
        if i >= warmup:
            walls.append(time.perf_counter() - t0)
            steps.append(pool.step_time - before)
    wall, step = float(np.median(walls)), float(np.median(steps))
    row = {"slots": slots, "busy": busy, "frame_ms": 1e3 * wall, "step_ms": 1e3 * step,
           "frame_ms_per_busy_slot": 1e3 * wall / busy}
    if parts:
        row.update(_frame_parts(pool, frames))
    assert pool.busy == busy, "a job ended or failed inside the timed frames"
    return row


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--spec", default="thesis-tshirt", help="dataset preset whose solver, garment and body to use")
    p.add_argument("--device", default=None)
    p.add_argument("--slots", type=int, default=128)
    p.add_argument("--busy", type=int, nargs="+", default=[128, 32, 8, 1])
    p.add_argument("--motion", default="walk")
    p.add_argument("--warmup", type=int, default=4)
    p.add_argument("--frames", type=int, default=10)
    p.add_argument("--parts", action="store_true", help="also time each part of a frame (module doc)")
    p.add_argument("--out", type=Path, default=None)
    a = p.parse_args(argv)

    from simgen._warp_log import quiet_warp
    from simgen.dataset import load_spec
    from simgen.dataset.execute import _load_body, _load_garment

    quiet_warp()
    spec = load_spec(a.spec).with_overrides(device=a.device)
    cfg = dataclasses.replace(spec.solver_config(), relax_frames=1, ramp_frames=2, rest_frames=1)
    body = _load_body(spec.body)
    garment = _load_garment(spec.garments[0], spec.body)
    runs = []
    for busy in a.busy:
        runs.append(_time_pool(garment, body, cfg, spec.fps, a.slots, min(busy, a.slots), a.motion, a.warmup,
                               a.frames, a.parts))
        print(json.dumps(runs[-1]), file=sys.stderr, flush=True)
    result = {"benchmark": "pool_occupancy", "date": time.strftime("%Y-%m-%d"),
              "device": _device(spec.resolved_device()), "commit": _commit(), "spec": spec.name,
              "sizes": {"garment": garment.name, "vertices": int(len(garment.vertices)), "slots": a.slots,
                        "substeps": cfg.substeps, "motion": a.motion, "timed_frames": a.frames},
              "runs": runs}
    _emit(result, a.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
