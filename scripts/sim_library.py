"""Simulate one garment on library motions and report per-motion quality (GPU machine friendly).

For each motion: runs :func:`simgen.sim.simulate` (thesis start protocol, then the clip), saves
OUT/GARMENT_MOTION.npz (positions float16 for viewing, faces, fps, motion name, summary)
and prints one JSON line: frames, seconds per frame, NaN, vertices inside the body at output frames
(self-intersections counted apart), retries, and membrane strain (largest principal stretch - 1 of
every triangle against its template) mean and max. No USD or VTK is needed here; make USD/MP4 on
the CPU machine with scripts/sim_render.py.

    python scripts/sim_library.py --garment tshirt --motions walk run cmu_131_03_hop --out runs/ --device cuda:0
"""

from __future__ import annotations

import argparse
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
    parser.add_argument("--motions", nargs="+", default=["walk"])
    parser.add_argument("--frames", type=int, default=None, help="first N frames of each clip")
    parser.add_argument("--device", default=None)
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args()

    from simgen.body import load
    from simgen.garment import load_garment
    from simgen.motion import load_motion
    from simgen.sim import SimulationConfig, simulate

    body = load("open")
    garment = load_garment(args.garment, body=body)
    args.out.mkdir(parents=True, exist_ok=True)
    summary = []
    for name in args.motions:
        clip = load_motion(name)
        config = SimulationConfig(record_body=True, device=args.device)
        t0 = time.perf_counter()
        result = simulate(garment, body, clip, None, config, frames=args.frames)
        wall = time.perf_counter() - t0
        pos = result.positions.astype(np.float64)
        stretch = principal_stretch(garment.vertices, pos, garment.faces.astype(np.int64)) - 1.0
        row = {
            "garment": garment.name, "motion": name, "frames": result.num_frames,
            "protocol_frames": int(len(result.protocol_positions)),
            "seconds_per_frame": wall / (result.num_frames + len(result.protocol_positions)),
            "nan": bool(not np.all(np.isfinite(pos))),
            "max_inside_regular": int(np.max(result.stats["inside_count"] - result.stats["self_intersection_count"])),
            "max_depth_regular_mm": 1e3 * float(np.max(result.stats["max_depth_regular"])),
            "max_self_intersection_vertices": int(np.max(result.stats["self_intersection_count"])),
            "retries": int(np.sum(result.stats["retries"])),
            "strain_mean": float(np.mean(stretch)), "strain_max": float(np.max(stretch)),
            "commit": os.environ.get("SIMGEN_COMMIT", "unknown"),
        }
        # The body is not stored (it would dominate the file); sim_render.py poses it again from the clip.
        np.savez_compressed(args.out / f"{garment.name}_{name}.npz", positions=result.positions.astype(np.float16),
                            faces=result.faces, fps=result.fps, motion=name, summary=json.dumps(row))
        print(json.dumps(row), flush=True)
        summary.append(row)
    (args.out / f"{garment.name}_summary.json").write_text(json.dumps(summary, indent=2) + "\n")


if __name__ == "__main__":
    main()
