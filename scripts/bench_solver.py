"""Benchmark the implicit solver against Newton 1.8's cloth solvers (VBD, Style3D) in the same run.

Two measurements of our solver, then the peers:

- motion: the T-shirt on the open body doing a library motion through :func:`simgen.sim.simulate_batch`
  (start protocol, then the clip; 30 fps frames of ``--substeps`` solver steps; the body is skinned
  on the device at every substep and its BVHs refit). N jobs of one batch have different body
  shapes (betas drawn uniformly in [-2, 2] for the first 4 components, instance 0 at zero).
  ms/frame is the median, over the animated frames, of the frame's stepping time (posing, refits,
  solver; a whole frame is one CUDA graph on CUDA), synchronised; per-frame statistics (winding-number
  penetration query, copy to the host) are reported apart as the total wall time per frame.
- static: the T-shirt draping onto the body held in rest pose, N copies stepping together, the
  frame captured as one CUDA graph: the same setting as the Newton peers.
- peers (``--peers vbd style3d``): scripts/bench_newton_peer.py on the same garment, body and
  frames (static body; VBD with ``--vbd-iterations`` iterations per substep).

Prints one JSON line per run and writes the whole result (device, commit, sizes, medians, ratios)
to --out.

    python scripts/bench_solver.py --device cuda:0 --motion walk --batches 1 16 64 --frames 60 \\
        --peers vbd style3d --out bench.json
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import warp as wp

REPO = Path(__file__).resolve().parents[1]


def commit() -> str:
    """The git commit measured; the device machine gets a copy of the tree without .git, so the
    caller passes it in SIMGEN_COMMIT there."""
    if os.environ.get("SIMGEN_COMMIT"):
        return os.environ["SIMGEN_COMMIT"]
    try:
        return subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=REPO, capture_output=True, text=True,
                              check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def used_memory_mb(device) -> float | None:
    d = wp.get_device(device)
    if not d.is_cuda:
        return None
    return (d.total_memory - d.free_memory) / 2**20


def shape_batch(n: int, num_betas: int, seed: int = 0) -> np.ndarray:
    """(n, 4) betas: row 0 zero, the others uniform in [-2, 2] (the thesis-tshirt range)."""
    rng = np.random.default_rng(seed)
    b = rng.uniform(-2.0, 2.0, size=(n, min(4, num_betas)))
    b[0] = 0.0
    return b


def solver_config(self_contact: bool, newton_iterations: int | None = None):
    """The bench's SolverConfig; newton_iterations None: the solver's default."""
    from simgen.sim import SolverConfig
    from simgen.sim.energies import SelfContactParams

    extra = {} if newton_iterations is None else {"newton_iterations": newton_iterations}
    return SolverConfig(self_contact=SelfContactParams() if self_contact else None, **extra)


def run_motion(garment, body, motion: str, n: int, *, device: str, frames: int, substeps: int,
               cuda_graph: bool, self_contact: bool = False, newton_iterations: int | None = None,
               preset=None) -> dict:
    """preset: a DatasetSpec whose simulation config (material, solver settings, substeps, protocol)
    replaces the bench's own (substeps, self_contact and newton_iterations are then the spec's)."""
    from dataclasses import replace

    from simgen.sim import SimulationConfig, SimulationFailure, SimulationJob, simulate_batch

    betas = shape_batch(n, body.num_betas)
    jobs = [SimulationJob(motion, betas=betas[i], frames=frames, key=str(i)) for i in range(n)]
    if preset is not None:
        cfg = replace(preset.solver_config(), device=device, cuda_graph=cuda_graph)
        substeps, self_contact = cfg.substeps, preset.self_contact
        newton_iterations = cfg.solver.newton_iterations
    else:
        cfg = SimulationConfig(substeps=substeps, device=device, cuda_graph=cuda_graph,
                               solver=solver_config(self_contact, newton_iterations))
        newton_iterations = cfg.solver.newton_iterations
    memory = {"before": used_memory_mb(device), "built": None}

    def on_frame(done, total, phase):
        if done == 1:
            memory["built"] = used_memory_mb(device)

    t0 = time.perf_counter()
    results = simulate_batch(garment, body, jobs, cfg, progress=on_frame)
    wall = time.perf_counter() - t0
    ok = [r for r in results if not isinstance(r, SimulationFailure)]
    r0 = ok[0]
    step = r0.stats["step_time"][1:]                       # animated frames that took steps
    median = float(np.median(step)) * 1e3
    per_substep = lambda key: float(np.mean(r0.stats[key][1:])) / substeps
    protocol_frames = len(r0.protocol_positions)
    row = {
        "mode": "motion", "motion": motion, "preset": preset.name if preset is not None else None,
        "instances": n, "self_contact": self_contact, "frames": frames, "substeps": substeps,
        "cuda_graph": bool(cuda_graph and wp.get_device(device).is_cuda),
        "ms_per_frame_median": median,
        "ms_per_frame_p90": float(np.percentile(step, 90)) * 1e3,
        "cloth_frames_per_s": n * 1e3 / median,
        # Frames redone for an instance that failed the guard make the mean the honest throughput.
        "ms_per_frame_mean": float(np.mean(step)) * 1e3,
        "cloth_frames_per_s_mean": n / float(np.mean(step)),
        "frames_with_retries": int(np.sum(np.sum([r.stats["retries"][1:] for r in ok], axis=0) > 0)),
        "newton_iterations": newton_iterations,
        "wall_ms_per_frame_with_stats": float(np.median(r0.stats["wall_time"][1:])) * 1e3,
        "total_wall_s": wall, "protocol_frames": protocol_frames,
        "newton_iterations_per_substep": per_substep("newton_iterations"),
        "cg_iterations_per_substep": per_substep("cg_iterations"),
        "failed_instances": len(results) - len(ok),
        "finite": bool(all(np.all(np.isfinite(r.positions)) for r in ok)),
        "max_depth_regular_mm": 1e3 * max(float(r.stats["max_depth_regular"].max()) for r in ok),
        "max_inside_regular": max(int((r.stats["inside_count"] - r.stats["self_intersection_count"]).max())
                                  for r in ok),
        "retries": int(sum(r.metadata["retries"] for r in ok)),
        # Instance-frames kept although they still failed the guard after the last retry.
        "unresolved": int(sum(int(np.sum(r.stats["unresolved"])) for r in ok)),
    }
    if memory["built"] is not None and memory["before"] is not None:
        row["gpu_memory_mb"] = memory["built"] - memory["before"]
        row["gpu_memory_mb_per_instance"] = row["gpu_memory_mb"] / n
    return row


def run_static(garment, body, n: int, *, device: str, frames: int, substeps: int, fps: float,
               warmup: int = 2, self_contact: bool = False, newton_iterations: int | None = None) -> dict:
    from simgen.sim import BodyCollider, ClothModel, ImplicitSolver

    before = used_memory_mb(device)
    model = ClothModel.concatenate([ClothModel.from_garment(garment, body=body, device=device)] * n)
    collider = BodyCollider.from_static(body.v_template, body.faces, num_instances=n, device=device)
    solver = ImplicitSolver(model, solver_config(self_contact, newton_iterations))
    state = model.state()
    dt = 1.0 / (fps * substeps)
    use_graph = wp.get_device(device).is_cuda

    def frame(deferred: bool):
        if deferred:
            solver.clear_deferred_guard()
        for _ in range(substeps):
            solver.step(state, state, collider, dt, deferred_guard=deferred)

    frame(False)                                          # loads kernels, takes the first contacts
    graph = None
    frame_counts = None
    if use_graph:
        # The host counters (Newton iterations) advance only while Python runs, i.e. at capture:
        # add the captured frame's increments at each replay (the CG count is kept on the device).
        before_counts = solver.host_counts()
        with wp.ScopedCapture(device=device, force_module_load=False) as capture:
            frame(True)
        graph = capture.graph
        frame_counts = {k: v - before_counts[k] for k, v in solver.host_counts().items()}
    solver.reset_stats()
    built = used_memory_mb(device)
    times = []
    for f in range(frames + warmup):
        wp.synchronize_device(device)
        t0 = time.perf_counter()
        if graph is not None:
            wp.capture_launch(graph)
            solver.add_host_counts(frame_counts)
        else:
            frame(False)
        wp.synchronize_device(device)
        if f >= warmup:
            times.append(time.perf_counter() - t0)
    x = state.positions.numpy()
    depth, share = collider.penetration(model, state.positions)
    median = float(np.median(times)) * 1e3
    st = solver.stats
    row = {
        "mode": "static", "instances": n, "self_contact": self_contact, "frames": frames, "substeps": substeps,
        "newton_iterations": solver.config.newton_iterations, "cuda_graph": graph is not None,
        "ms_per_frame_median": median, "cloth_frames_per_s": n * 1e3 / median,
        "cg_per_newton": st["cg_per_newton"],
        "guard_failures": int(solver.deferred_bad.numpy().astype(bool).sum()) if graph is not None else st["retries"],
        "finite": bool(np.all(np.isfinite(x))),
        "max_inside_depth_mm": 1e3 * float(depth.max()),
        "y_min": float(x[:, 1].min()),
    }
    if before is not None:
        row["gpu_memory_mb"] = built - before
        row["gpu_memory_mb_per_instance"] = (built - before) / n
    return row


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--device", default=None)
    parser.add_argument("--garment", default="tshirt")
    parser.add_argument("--motion", default="walk")
    parser.add_argument("--batches", type=int, nargs="+", default=[1, 16, 64])
    parser.add_argument("--frames", type=int, default=60, help="animated (or static) frames timed")
    parser.add_argument("--substeps", type=int, default=10)
    parser.add_argument("--fps", type=float, default=30.0)
    parser.add_argument("--modes", nargs="+", default=["motion", "static"], choices=["motion", "static"])
    parser.add_argument("--no-graph", action="store_true", help="motion mode without CUDA graphs (for the profile)")
    parser.add_argument("--self-contact", choices=["off", "on", "both"], default="both",
                        help="our runs without and/or with cloth self-contact")
    parser.add_argument("--newton-iterations", type=int, default=None,
                        help="our solver's Newton iterations per substep (default: the solver's)")
    parser.add_argument("--peers", nargs="*", default=[], choices=["vbd", "style3d"])
    parser.add_argument("--vbd-iterations", type=int, default=10)
    parser.add_argument("--preset", default=None,
                        help="motion mode with a dataset spec's garment, material and solver settings (a preset "
                             "name or TOML path; --substeps, --self-contact and --newton-iterations then come "
                             "from the spec)")
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args()
    if args.newton_iterations is not None and args.newton_iterations < 1:
        parser.error(f"--newton-iterations must be >= 1, got {args.newton_iterations}")

    from simgen.body import load
    from simgen.garment import load_garment

    wp.config.quiet = True
    wp.init()
    device = args.device or str(wp.get_preferred_device())
    dev = wp.get_device(device)
    preset = None
    if args.preset is not None:
        from simgen.dataset import load_spec

        preset = load_spec(args.preset)
        args.garment, args.substeps, args.fps = preset.garments[0], preset.substeps, preset.fps
        args.self_contact = "on" if preset.self_contact else "off"
    body = load("open")
    garment = load_garment(args.garment, body=body)
    result = {
        "benchmark": "solver",
        "device": dev.name if dev.is_cuda else platform.processor() or "cpu",
        "device_alias": device,
        "host": platform.node(),
        "commit": commit(),
        "warp": wp.__version__,
        "garment": {"name": garment.name, "vertices": garment.num_vertices, "triangles": garment.num_triangles},
        "body_vertices": body.num_vertices,
        "substeps_per_frame": args.substeps, "fps": args.fps, "preset": args.preset,
        "runs": [],
    }

    def emit(row):
        result["runs"].append(row)
        print(json.dumps(row), flush=True)
        if args.out is not None:  # after every run, so a cut benchmark keeps what it measured
            args.out.write_text(json.dumps(result, indent=2) + "\n")

    contact_modes = {"off": [False], "on": [True], "both": [False, True]}[args.self_contact]
    for n in args.batches:
        for sc in contact_modes:
            if "motion" in args.modes:
                emit(run_motion(garment, body, args.motion, n, device=device, frames=args.frames,
                                substeps=args.substeps, cuda_graph=not args.no_graph, self_contact=sc,
                                newton_iterations=args.newton_iterations, preset=preset))
            if "static" in args.modes:
                emit(run_static(garment, body, n, device=device, frames=args.frames, substeps=args.substeps,
                                fps=args.fps, self_contact=sc, newton_iterations=args.newton_iterations))
    if args.peers:
        sys.path.insert(0, str(Path(__file__).resolve().parent))
        from bench_newton_peer import run_newton_peer

        for solver in args.peers:
            for n in args.batches:
                try:
                    row = run_newton_peer(solver, garment.vertices, garment.faces, body.v_template, body.faces,
                                          instances=n, frames=args.frames, substeps=args.substeps, fps=args.fps,
                                          iterations=args.vbd_iterations, device=device)
                except Exception as exc:  # a peer failing must not lose our own numbers
                    row = {"error": f"{type(exc).__name__}: {exc}"}
                emit({"mode": "peer", "peer": f"newton-{solver}", "instances": n, **row})
    # Ratios: our static drape against each peer at the same instance count, and our motion run
    # (without self-contact: the peers run without it too).
    ours = {(r["mode"], r["instances"]): r for r in result["runs"]
            if r["mode"] in ("motion", "static") and not r["self_contact"]}
    ratios = []
    for r in result["runs"]:
        if r["mode"] != "peer" or "cloth_frames_per_s" not in r:
            continue
        for mode in ("static", "motion"):
            o = ours.get((mode, r["instances"]))
            if o:
                ratios.append({"ours": mode, "peer": r["peer"], "instances": r["instances"],
                               "throughput_ratio": o["cloth_frames_per_s"] / r["cloth_frames_per_s"]})
    result["ratios"] = ratios
    text = json.dumps(result, indent=2)
    print(text)
    if args.out is not None:
        args.out.write_text(text + "\n")


if __name__ == "__main__":
    main()
