"""Untangling on real tangles: simulate a garment without self-contact, untangle every tangled frame.

Simulates GARMENT in MOTION at one shape with a dataset preset's solver settings and self-contact
off (CPU by default: the coarse T-shirt in ``kick`` at beta 1 = +2 tangles with two Newton
iterations per substep), then runs
:func:`simgen.garment.untangle.untangle` on each frame with crossing edges in two ways: alone
(global intersection analysis only), and as the frame-end repair does it, with a reference: the
previous frame as repaired (the last clean frame before the first tangle). Prints one JSON object
(and writes it to --out): device, commit, sizes, and per way the frames untangled, rounds, largest
move [m] and seconds.

    python scripts/untangle_replay.py --garment tshirt_1k --motion kick --betas 0 2 --frames 60 --newton-iterations 2
"""

from __future__ import annotations

import argparse
import json
import time
from dataclasses import replace

import numpy as np

from _record import commit  # scripts/_record.py (the script's own folder is on sys.path)


def simulate_tangled(args) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Positions [m] (T, V, 3), faces and crossing edges per frame (T,) of the run without self-contact."""
    from simgen import body as body_pkg
    from simgen.dataset.spec import load_spec
    from simgen.garment.library import load_garment
    from simgen.motion.library import load_motion
    from simgen.motion.ops import trim
    from simgen.sim import simulate

    cfg = load_spec(args.preset).solver_config()
    solver = replace(cfg.solver, self_contact=None, **({} if args.newton_iterations is None
                                                      else {"newton_iterations": args.newton_iterations}))
    cfg = replace(cfg, device=args.device, solver=solver,
                  relax_frames=2, ramp_frames=5, rest_frames=2)
    body = body_pkg.load("open")
    clip = trim(load_motion(args.motion), args.start, args.start + args.frames / 30.0 + 0.5)
    result = simulate(load_garment(args.garment, body=body), body, clip, np.array(args.betas), cfg, frames=args.frames)
    return result.positions.astype(np.float64), result.faces, result.stats["crossing_edges"]


def replay(x: np.ndarray, faces: np.ndarray, crossing: np.ndarray, with_reference: bool) -> dict:
    """Untangle every frame with crossings; with_reference: the previous frame as repaired."""
    from simgen.garment.crossings import CrossingCounter
    from simgen.garment.untangle import untangle

    counter = CrossingCounter(faces, x.shape[1])
    tangled = np.flatnonzero(crossing)
    rows, reference = [], (x[tangled[0] - 1] if len(tangled) and tangled[0] > 0 else None)
    for k in tangled:
        t = time.perf_counter()
        r = untangle(x[k], faces, counter=counter, reference=reference if with_reference else None)
        rows.append({"frame": int(k), "crossings": r.crossings_before, "left": r.crossings_after, "rounds": r.rounds,
                     "max_move_m": round(r.max_displacement, 4), "seconds": round(time.perf_counter() - t, 3)})
        if r.untangled:
            reference = r.positions
    done = [row for row in rows if row["left"] == 0]
    return {"frames_tangled": len(rows), "frames_untangled": len(done),
            "rounds_max": max((row["rounds"] for row in done), default=0),
            "max_move_m": max((row["max_move_m"] for row in done), default=0.0), "frames": rows}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--garment", default="tshirt_1k")
    p.add_argument("--motion", default="kick")
    p.add_argument("--betas", type=float, nargs="+", default=[0.0, 2.0])
    p.add_argument("--start", type=float, default=1.0, help="clip start [s]")
    p.add_argument("--frames", type=int, default=60)
    p.add_argument("--preset", default="thesis-tshirt", help="dataset preset whose solver settings are used")
    p.add_argument("--newton-iterations", type=int, default=None, help="instead of the preset's")
    p.add_argument("--device", default="cpu")
    p.add_argument("--out", help="also write the JSON to this file")
    args = p.parse_args()
    if args.newton_iterations is not None and args.newton_iterations < 1:
        p.error(f"--newton-iterations must be >= 1, got {args.newton_iterations}")
    x, faces, crossing = simulate_tangled(args)
    out = {"benchmark": "untangle_replay", "device": args.device, "commit": commit(), "garment": args.garment,
           "motion": args.motion, "betas": args.betas, "frames": args.frames, "vertices": int(x.shape[1]),
           "newton_iterations": args.newton_iterations,
           "alone": replay(x, faces, crossing, False), "with_reference": replay(x, faces, crossing, True)}
    print(json.dumps(out))
    if args.out:
        with open(args.out, "w") as fh:
            json.dump(out, fh, indent=1)


if __name__ == "__main__":
    main()
