"""Simulate one garment on library motions and report per-motion quality (GPU machine friendly).

All motions run as one batch of :func:`simgen.sim.simulate_batch` (one instance per motion, the
batch runs to the longest clip; thesis start protocol, then each clip), or one after another with
``--sequential``. For each motion it saves OUT/GARMENT_MOTION.npz (positions, float16 for viewing or
float32 with ``--float32`` for the physics report; faces, fps, motion name, summary) and prints one
JSON line: frames, seconds per frame, NaN, vertices inside the body at output frames
(self-intersections counted apart), retries, and membrane strain (largest principal stretch - 1 of
every triangle against its template) mean and max. No USD or VTK is needed here; make USD/MP4 on
the CPU machine with scripts/sim_render.py.

    python scripts/sim_library.py --garment tshirt --motions all --out runs/ --device cuda:0
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import time
from pathlib import Path

import numpy as np


def principal_stretch(rest: np.ndarray, posed: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Largest principal stretch of each triangle, (T, F), from rest (V, 3) and posed (T, V, 3) [m]."""
    e1 = rest[faces[:, 1]] - rest[faces[:, 0]]
    e2 = rest[faces[:, 2]] - rest[faces[:, 0]]
    u = e1 / np.linalg.norm(e1, axis=1, keepdims=True)
    n = np.cross(e1, e2)
    w = np.cross(n / np.linalg.norm(n, axis=1, keepdims=True), u)
    Dm = np.stack([np.stack([np.sum(e1 * u, 1), np.sum(e2 * u, 1)], 1),
                   np.stack([np.sum(e1 * w, 1), np.sum(e2 * w, 1)], 1)], 1)  # (F, 2, 2)
    Dm_inv = np.linalg.inv(Dm)
    d1 = posed[:, faces[:, 1]] - posed[:, faces[:, 0]]
    d2 = posed[:, faces[:, 2]] - posed[:, faces[:, 0]]
    Ds = np.stack([d1, d2], axis=-1)  # (T, F, 3, 2)
    F = Ds @ Dm_inv[None]
    return np.sqrt(np.linalg.eigvalsh(np.swapaxes(F, -1, -2) @ F)[..., -1])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--garment", default="tshirt")
    parser.add_argument("--motions", nargs="+", default=["walk"], help="library names, or 'all'")
    parser.add_argument("--sequential", action="store_true", help="one simulate() per motion instead of one batch")
    parser.add_argument("--float32", action="store_true", help="store positions as float32 (default float16)")
    parser.add_argument("--frames", type=int, default=None, help="first N frames of each clip")
    parser.add_argument("--device", default=None)
    parser.add_argument("--self-contact", action="store_true", help="cloth self-contact on (2 mm thickness)")
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args()

    from simgen.body import load
    from simgen.garment import load_garment
    from simgen.motion import load_motion
    from simgen.motion.library import list_motions
    from simgen.sim import SimulationConfig, SimulationFailure, SimulationJob, simulate, simulate_batch
    from simgen.sim.energies import SelfContactParams

    body = load("open")
    garment = load_garment(args.garment, body=body)
    args.out.mkdir(parents=True, exist_ok=True)
    names = [m["name"] for m in list_motions()] if args.motions == ["all"] else args.motions
    config = SimulationConfig(device=args.device)
    if args.self_contact:
        config = dataclasses.replace(config, solver=dataclasses.replace(config.solver,
                                                                        self_contact=SelfContactParams()))
    runs = []
    if args.sequential:
        for name in names:
            t0 = time.perf_counter()
            result = simulate(garment, body, load_motion(name), None, config, frames=args.frames)
            runs.append((name, result, time.perf_counter() - t0, 1))
    else:
        t0 = time.perf_counter()
        results = simulate_batch(garment, body, [SimulationJob(n, frames=args.frames, key=n) for n in names], config)
        wall = time.perf_counter() - t0
        runs = [(n, r, wall, len(names)) for n, r in zip(names, results)]
    summary = []
    for name, result, wall, batch in runs:
        if isinstance(result, SimulationFailure):
            row = {"garment": garment.name, "motion": name, "failed": result.message, "phase": result.phase,
                   "frame": result.frame}
            print(json.dumps(row), flush=True)
            summary.append(row)
            continue
        pos = result.positions.astype(np.float64)
        stretch = principal_stretch(garment.vertices, pos, garment.faces.astype(np.int64)) - 1.0
        row = {
            "garment": garment.name, "motion": name, "frames": result.num_frames,
            "protocol_frames": int(len(result.protocol_positions)), "batch_size": batch,
            "batch_wall_s": wall,
            "step_ms_per_batch_frame": 1e3 * float(np.median(result.stats["step_time"][1:])) if result.num_frames > 1
            else None,
            "nan": bool(not np.all(np.isfinite(pos))),
            "max_inside_regular": int(np.max(result.stats["inside_count"] - result.stats["self_intersection_count"])),
            "self_contact": bool(args.self_contact),
            "max_depth_regular_mm": 1e3 * float(np.max(result.stats["max_depth_regular"])),
            "max_depth_regular_frame": int(np.argmax(result.stats["max_depth_regular"])),
            "frames_over_1mm_regular": int(np.sum(result.stats["max_depth_regular"] > 1.0e-3)),
            "max_self_intersection_vertices": int(np.max(result.stats["self_intersection_count"])),
            "retries": int(np.sum(result.stats["retries"])),
            "strain_mean": float(np.mean(stretch)), "strain_max": float(np.max(stretch)),
            "commit": os.environ.get("SIMGEN_COMMIT", "unknown"),
        }
        # The body is not stored (it would dominate the file); sim_render.py poses it again from the clip.
        dtype = np.float32 if args.float32 else np.float16
        np.savez_compressed(args.out / f"{garment.name}_{name}.npz", positions=result.positions.astype(dtype),
                            faces=result.faces, fps=result.fps, motion=name, summary=json.dumps(row))
        print(json.dumps(row), flush=True)
        summary.append(row)
    (args.out / f"{garment.name}_summary.json").write_text(json.dumps(summary, indent=2) + "\n")


if __name__ == "__main__":
    main()
