"""Benchmark the implicit solver: the T-shirt draping on the open body in rest pose.

For each batch size N, N copies of the garment (one instance each, each with its own body mesh)
step together; a 30 fps frame is ``--substeps`` solver steps. Prints one JSON object (device,
commit, sizes, medians) and writes it to --out. The body is static here (rest pose): this measures
the solver (assembly, PCG, contact, projection), not body skinning. Graph capture is not used yet,
so launch overhead is included.

    python scripts/bench_solver.py --device cuda:0 --batches 1 16 64 --frames 20 --out bench.json
"""

from __future__ import annotations

import argparse
import json
import platform
import subprocess
import time
from pathlib import Path

import numpy as np
import warp as wp

REPO = Path(__file__).resolve().parents[1]


def commit() -> str:
    """The git commit measured; the device machine gets a copy of the tree without .git, so the
    caller passes it in SIMGEN_COMMIT there."""
    import os

    if os.environ.get("SIMGEN_COMMIT"):
        return os.environ["SIMGEN_COMMIT"]
    try:
        return subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=REPO, capture_output=True, text=True,
                              check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def run_batch(garment, body, n: int, *, device: str, frames: int, substeps: int, fps: float,
              newton_iterations: int, cg_iterations: int) -> dict:
    from simgen.sim import ClothModel, ImplicitSolver, SolverConfig
    from simgen.sim.collider import BodyCollider

    model = ClothModel.concatenate([ClothModel.from_garment(garment, device=device)] * n)
    collider = BodyCollider.from_static(body.v_template, body.faces, num_instances=n, device=device)
    config = SolverConfig(newton_iterations=newton_iterations, cg_iterations=cg_iterations)
    solver = ImplicitSolver(model, config)
    solver.load()
    s0, s1 = model.state(), model.state()
    dt = 1.0 / (fps * substeps)
    frame_ms = []
    for f in range(frames + 2):  # two warm-up frames
        wp.synchronize_device(device)
        t0 = time.perf_counter()
        for _ in range(substeps):
            solver.step(s0, s1, collider, dt)
            s0, s1 = s1, s0
        wp.synchronize_device(device)
        if f >= 2:
            frame_ms.append(1e3 * (time.perf_counter() - t0))
    stats = solver.stats
    x = s0.positions.numpy()
    median = float(np.median(frame_ms))
    return {
        "instances": n,
        "vertices_total": int(model.vertex_count) if hasattr(model, "vertex_count") else int(len(x)),
        "ms_per_frame_median": median,
        "cloth_frames_per_s": n * 1e3 / median,
        "cg_per_newton": stats.get("cg_per_newton"),
        "retries": stats.get("retries"),
        "max_penetration_m": stats.get("max_penetration"),
        "finite": bool(np.all(np.isfinite(x))),
        "gpu_memory_mb": (wp.get_device(device).total_memory - wp.get_device(device).free_memory) / 2**20
        if wp.get_device(device).is_cuda else None,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--device", default=None)
    parser.add_argument("--garment", default="tshirt")
    parser.add_argument("--batches", type=int, nargs="+", default=[1, 16, 64])
    parser.add_argument("--frames", type=int, default=20)
    parser.add_argument("--substeps", type=int, default=10)
    parser.add_argument("--fps", type=float, default=30.0)
    parser.add_argument("--newton-iterations", type=int, default=1)
    parser.add_argument("--cg-iterations", type=int, default=50)
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args()

    from simgen.body import load
    from simgen.garment import load_garment

    wp.config.quiet = True
    wp.init()
    device = args.device or str(wp.get_preferred_device())
    body = load("open")
    garment = load_garment(args.garment, body=body)
    result = {
        "benchmark": "solver_static_drape",
        "device": wp.get_device(device).name if hasattr(wp.get_device(device), "name") else device,
        "device_alias": device,
        "host": platform.node(),
        "commit": commit(),
        "warp": wp.__version__,
        "garment": {"name": garment.name, "vertices": garment.num_vertices, "triangles": garment.num_triangles},
        "body_vertices": body.num_vertices,
        "substeps_per_frame": args.substeps,
        "fps": args.fps,
        "newton_iterations": args.newton_iterations,
        "cg_iterations": args.cg_iterations,
        "graph_capture": False,
        "frames_timed": args.frames,
        "runs": [],
    }
    for n in args.batches:
        result["runs"].append(run_batch(garment, body, n, device=device, frames=args.frames, substeps=args.substeps,
                                        fps=args.fps, newton_iterations=args.newton_iterations,
                                        cg_iterations=args.cg_iterations))
        print(json.dumps(result["runs"][-1]), flush=True)
    text = json.dumps(result, indent=2)
    print(text)
    if args.out is not None:
        args.out.write_text(text + "\n")


if __name__ == "__main__":
    main()
