"""What idle slots cost a simulation pool: frame time of a pool of N slots with K of them busy.

A :class:`simgen.sim.SimulationPool` of ``--slots`` N (the dataset preset's solver settings, its
garment and body) runs K jobs of ``--motion`` at once (K from ``--busy``), the others idle (pinned,
no body). The protocol is cut to 1 + 2 + 1 frames so that the timed frames are animated ones; the
first ``--warmup`` frames (kernel loads, graph captures) are not timed. Per K: the median wall time
of a pool frame (stepping, statistics, host copies) and of its stepping alone, and that per busy
slot. If idle slots cost the kernels nothing, the frame time falls with K; if they cost as much as
busy ones, it stays flat.

    python scripts/bench_pool_occupancy.py --device cuda:0 --slots 128 --busy 128 32 8 1 --out occ.json

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


def _time_pool(garment, body, cfg, fps: float, slots: int, busy: int, motion: str, warmup: int, frames: int) -> dict:
    from simgen.sim import SimulationJob, SimulationPool

    pool = SimulationPool(garment, body, slots, cfg, fps=fps)
    for k in range(busy):
        pool.submit(SimulationJob(motion, frames=warmup + frames + 2, key=f"job{k}"))
    walls, steps = [], []
    for i in range(warmup + frames):
        t0 = time.perf_counter()
        before = pool.step_time
        pool.step()
        if i >= warmup:
            walls.append(time.perf_counter() - t0)
            steps.append(pool.step_time - before)
    assert pool.busy == busy, "a job ended or failed inside the timed frames"
    wall, step = float(np.median(walls)), float(np.median(steps))
    return {"slots": slots, "busy": busy, "frame_ms": 1e3 * wall, "step_ms": 1e3 * step,
            "frame_ms_per_busy_slot": 1e3 * wall / busy}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--spec", default="thesis-tshirt", help="dataset preset whose solver, garment and body to use")
    p.add_argument("--device", default=None)
    p.add_argument("--slots", type=int, default=128)
    p.add_argument("--busy", type=int, nargs="+", default=[128, 32, 8, 1])
    p.add_argument("--motion", default="walk")
    p.add_argument("--warmup", type=int, default=4)
    p.add_argument("--frames", type=int, default=10)
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
                               a.frames))
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
