"""Validate the soft-tissue simulation (issue 25 part 1) on the bundled open body; prints (and saves) JSON.

    python scripts/softtissue_validate.py --device cpu --json st.json
    python scripts/softtissue_validate.py --clips run:0:5 jump:0:5.5 --shapes -2 0 2 --device cuda:0

For each clip window (library motion, start and end [s]) and each shape (the value of beta 2, the
open body's body-fat axis: its BMI proxy rises from about 16 at -2 to 32 at +2), the simulation's
displacement Delta at the body's vertices, by region (each vertex takes the region of its
tetrahedron): the peak |Delta| over frames and vertices (static sag included), the peak of its
motion |Delta_t - Delta_0| (Delta_0: the static equilibrium of the first frame), and the smallest
det(I + grad u) (> 0: no tetrahedron inverted). Then the regions' first modal frequencies at beta = 0
(lowest mode with at least 30% of its kinetic energy in the region). Expected (the issue's
targets): belly and chest peaks of 1-3 cm in running and jumping, near zero on head and hands,
rising with body mass; belly and chest frequencies of 2-15 Hz.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np


def _commit() -> str:
    if os.environ.get("SIMGEN_COMMIT"):
        return os.environ["SIMGEN_COMMIT"]
    try:
        return subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=Path(__file__).resolve().parents[1],
                              capture_output=True, text=True, check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--clips", nargs="+", default=["run:0:3", "jump:0:2"],
                   help="motion:start:end [s]; from a standing start, where the first frame is at rest")
    p.add_argument("--shapes", nargs="+", type=float, default=[-2.0, 0.0, 2.0], help="values of beta 2")
    p.add_argument("--device", default="cpu")
    p.add_argument("--json")
    a = p.parse_args(argv)

    import warp as wp

    wp.config.quiet = True
    from simgen import body as body_pkg
    from simgen.motion.library import load_motion
    from simgen.motion.ops import trim
    from simgen.softtissue import REGIONS, FleshParams, flesh_mesh, simulate_softtissue
    from simgen.softtissue.model import FleshModel, body_mass_proxy
    from simgen.softtissue.modes import region_modes
    from simgen.softtissue.solver import FleshSolver

    body = body_pkg.load("open")
    mesh = flesh_mesh(body)
    params = FleshParams()
    betas = np.zeros((len(a.shapes), body.num_betas))
    betas[:, 2] = a.shapes
    vertex_region = mesh.region[mesh.skin_tet]
    result = {"benchmark": "softtissue_validate", "date": time.strftime("%Y-%m-%d"), "commit": _commit(),
              "device": a.device, "mesh": {"nodes": mesh.num_nodes, "tets": mesh.num_tets}, "params": vars(params),
              "shapes": {str(s): {"beta2": s, "bmi_proxy": body_mass_proxy(body, b, params.density)}
                         for s, b in zip(a.shapes, betas)}, "clips": {}}
    for spec in a.clips:
        name, start, end = spec.split(":")
        clip = trim(load_motion(name), float(start), float(end))
        t0 = time.perf_counter()
        seqs = simulate_softtissue(body, clip, betas, params, mesh=mesh, device=a.device,
                                   subjects=[f"beta2={s:g}" for s in a.shapes],
                                   progress=lambda d, n: print(f"{name}: {d}/{n}", file=sys.stderr, flush=True))
        wall = time.perf_counter() - t0
        per_shape = {}
        for s, seq in zip(a.shapes, seqs):
            d = seq.displacements.astype(np.float64)
            mag = np.linalg.norm(d, axis=2)
            motion = np.linalg.norm(d - d[:1], axis=2)
            per_shape[str(s)] = {
                "layer_m": seq.meta["layer_m"], "min_det": seq.meta["min_det"],
                "cg_iterations_max": seq.meta["cg_iterations_max"],
                "peak_m": {r: float(mag[:, vertex_region == i].max()) for i, r in enumerate(REGIONS)},
                "peak_motion_m": {r: float(motion[:, vertex_region == i].max()) for i, r in enumerate(REGIONS)},
            }
        result["clips"][spec] = {"frames": int(seqs[0].num_frames), "wall_s": wall, "shapes": per_shape}
        print(json.dumps({spec: result["clips"][spec]}, indent=1), file=sys.stderr, flush=True)
    model = FleshModel.for_body(mesh, body, np.zeros((1, body.num_betas)), params, device=a.device)
    node_region = np.zeros(mesh.num_nodes, dtype=int)
    node_region[mesh.tets.ravel()] = np.repeat(mesh.region, 4)
    result["first_mode_hz"] = region_modes(FleshSolver(model), {r: node_region == i for i, r in enumerate(REGIONS)},
                                           count=150, share=0.3)
    text = json.dumps(result, indent=2)
    print(text)
    if a.json:
        Path(a.json).write_text(text + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
