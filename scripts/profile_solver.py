"""Profile one 30 fps frame of the implicit solver: GPU time per kernel, launches, and graph replay.

The T-shirt drapes onto the open body in rest pose (the static setting of bench_solver.py), N copies
stepping together. After warm-up frames, ``--frames`` frames run eagerly with the guard deferred
(exactly the launches a captured frame holds, no host reads) under Warp's activity timing
(``wp.timing_begin``); every kernel's GPU time is summed per frame and grouped by solver phase.
The same frame is then captured as a CUDA graph and its replay timed, so the JSON shows how the
frame time splits into kernel work and what is left (launch gaps, idle).

``term_split`` then times the membrane and bending launches alone with each output on its own
(energy only, gradient only, gradient + Hessian, all three): the energy goes into one scalar per
instance, the gradient and Hessian blocks into per-vertex and per-slot addresses, so the split tells
which of the two kinds of atomics costs the time.

    python scripts/profile_solver.py --device cuda:0 --batches 1 64 --self-contact both --out profile.json
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections import defaultdict
from pathlib import Path

import numpy as np
import warp as wp

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_solver import commit  # noqa: E402

# Warp names a kernel "forward kernel <factory>__locals__<function>_<hash>"; the factory (one per
# energy file or solver module) decides the phase. Memory operations keep Warp's own names.
PHASES = {
    "pcg_kernels": "pcg",
    "membrane_kernels": "assembly", "bending_kernels": "assembly", "inertia_kernels": "assembly",
    "gravity_kernels": "assembly", "damping_kernels": "assembly", "friction_kernels": "assembly",
    "contact_kernels": "body contact (BVH queries)",
    "self_contact_kernels": "self-contact",
    "collider_kernels": "body: posing, refit, projection",
    "solver_kernels": "integrator (predict, line search, guard)",
}


def phase_of(name: str) -> str:
    label = name.removeprefix("forward kernel ").strip()
    if "__locals__" in label:
        return PHASES.get(label.split("__locals__")[0], "other kernels")
    if label.startswith(("memcpy", "memset")):
        return "copies and memsets"
    return "other kernels"


def profile(garment, body, n: int, *, device: str, frames: int, substeps: int, fps: float, self_contact: bool,
            warmup: int = 3, preset=None) -> dict:
    """preset: a DatasetSpec whose material and solver settings replace the defaults."""
    from simgen.sim import BodyCollider, ClothModel, ImplicitSolver, SolverConfig
    from simgen.sim.energies import SelfContactParams

    material, config = None, SolverConfig(self_contact=SelfContactParams() if self_contact else None)
    if preset is not None:
        sim_config = preset.solver_config()
        material, config = sim_config.resolve_material(garment), sim_config.solver
    model = ClothModel.concatenate([ClothModel.from_garment(garment, material, body=body, device=device)] * n)
    collider = BodyCollider.from_static(body.v_template, body.faces, num_instances=n, device=device)
    solver = ImplicitSolver(model, config)
    state = model.state()
    dt = 1.0 / (fps * substeps)

    def frame(deferred: bool):
        if deferred:
            solver.clear_deferred_guard()
        for _ in range(substeps):
            solver.step(state, state, collider, dt, deferred_guard=deferred)

    for _ in range(warmup):
        frame(False)
    wp.synchronize_device(device)
    solver.reset_stats()
    wp.timing_begin(cuda_filter=wp.TIMING_ALL)
    t0 = time.perf_counter()
    for _ in range(frames):
        frame(True)
    wp.synchronize_device(device)
    eager_ms = (time.perf_counter() - t0) * 1e3 / frames
    results = wp.timing_end()
    cg = solver.stats["cg_per_newton"]

    per_kernel = defaultdict(lambda: [0.0, 0])
    for r in results:
        entry = per_kernel[r.name]
        entry[0] += r.elapsed
        entry[1] += 1
    kernels = sorted(({"name": k, "ms_per_frame": v[0] / frames, "launches_per_frame": v[1] / frames,
                       "phase": phase_of(k)} for k, v in per_kernel.items()), key=lambda e: -e["ms_per_frame"])
    gpu_ms = sum(e["ms_per_frame"] for e in kernels)
    phases = defaultdict(lambda: {"ms_per_frame": 0.0, "launches_per_frame": 0.0})
    for e in kernels:
        phases[e["phase"]]["ms_per_frame"] += e["ms_per_frame"]
        phases[e["phase"]]["launches_per_frame"] += e["launches_per_frame"]
    for p in phases.values():
        p["share_of_kernel_time"] = p["ms_per_frame"] / gpu_ms if gpu_ms > 0 else 0.0

    graph_ms = None
    if wp.get_device(device).is_cuda:
        with wp.ScopedCapture(device=device, force_module_load=False) as capture:
            frame(True)
        times = []
        for f in range(frames + 2):
            wp.synchronize_device(device)
            t0 = time.perf_counter()
            wp.capture_launch(capture.graph)
            wp.synchronize_device(device)
            if f >= 2:
                times.append(time.perf_counter() - t0)
        graph_ms = float(np.median(times)) * 1e3
    terms_ms = term_split(model, state.positions, solver.hessian, device)
    return {
        "term_split_ms_per_launch": terms_ms,
        "instances": n, "vertices": model.num_vertices, "self_contact": self_contact, "frames": frames,
        "substeps": substeps, "cg_per_newton": cg,
        "kernel_ms_per_frame": gpu_ms, "launches_per_frame": sum(e["launches_per_frame"] for e in kernels),
        "eager_ms_per_frame": eager_ms, "graph_ms_per_frame": graph_ms,
        "phases": dict(sorted(phases.items(), key=lambda kv: -kv[1]["ms_per_frame"])),
        "top_kernels": kernels[:20],
    }


def term_split(model, positions, hessian, device: str, repeats: int = 20) -> dict:
    """Milliseconds per launch of membrane and bending with each output alone and all together."""
    from simgen.sim.energies import eval_bending, eval_membrane

    energy, gradient = model.new_energy(), model.new_gradient()
    outputs = {"energy": dict(energy=energy), "gradient": dict(gradient=gradient),
               "gradient+hessian": dict(gradient=gradient, hessian=hessian),
               "all": dict(energy=energy, gradient=gradient, hessian=hessian)}
    split = {}
    for name, term in (("membrane", eval_membrane), ("bending", eval_bending)):
        split[name] = {}
        for label, kwargs in outputs.items():
            term(model, positions, **kwargs)  # warm-up (module load)
            wp.synchronize_device(device)
            t0 = time.perf_counter()
            for _ in range(repeats):
                term(model, positions, **kwargs)
            wp.synchronize_device(device)
            split[name][label] = (time.perf_counter() - t0) * 1e3 / repeats
    return split


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--device", default=None)
    parser.add_argument("--garment", default="tshirt")
    parser.add_argument("--batches", type=int, nargs="+", default=[1, 64])
    parser.add_argument("--frames", type=int, default=5)
    parser.add_argument("--substeps", type=int, default=10)
    parser.add_argument("--fps", type=float, default=30.0)
    parser.add_argument("--self-contact", choices=["off", "on", "both"], default="off")
    parser.add_argument("--preset", default=None,
                        help="a dataset spec's garment, material and solver settings (preset name or TOML path; "
                             "--substeps and --self-contact then come from the spec)")
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args()

    from simgen.body import load
    from simgen.garment import load_garment

    wp.config.quiet = True
    wp.init()
    device = args.device or str(wp.get_preferred_device())
    preset = None
    if args.preset is not None:
        from simgen.dataset import load_spec

        preset = load_spec(args.preset)
        args.garment, args.substeps, args.fps = preset.garments[0], preset.substeps, preset.fps
        args.self_contact = "on" if preset.self_contact else "off"
    body = load("open")
    garment = load_garment(args.garment, body=body)
    modes = {"off": [False], "on": [True], "both": [False, True]}[args.self_contact]
    result = {"benchmark": "solver_profile", "device": wp.get_device(device).name, "commit": commit(),
              "warp": wp.__version__, "garment": {"name": garment.name, "vertices": garment.num_vertices},
              "preset": args.preset,
              "runs": []}
    for n in args.batches:
        for sc in modes:
            row = profile(garment, body, n, device=device, frames=args.frames, substeps=args.substeps,
                          fps=args.fps, self_contact=sc, preset=preset)
            result["runs"].append(row)
            summary = {k: row[k] for k in ("instances", "self_contact", "kernel_ms_per_frame", "launches_per_frame",
                                           "eager_ms_per_frame", "graph_ms_per_frame", "cg_per_newton",
                                           "term_split_ms_per_launch")}
            summary["phases_ms"] = {p: round(v["ms_per_frame"], 3) for p, v in row["phases"].items()}
            summary["top"] = [(e["name"][:40], round(e["ms_per_frame"], 2), e["launches_per_frame"])
                              for e in row["top_kernels"][:10]]
            print(json.dumps(summary), flush=True)
            if args.out is not None:  # after every run, so a cut run keeps what it measured
                args.out.write_text(json.dumps(result, indent=2) + "\n")
    text = json.dumps(result, indent=2)
    if args.out is not None:
        args.out.write_text(text + "\n")
    else:
        print(text)


if __name__ == "__main__":
    main()
