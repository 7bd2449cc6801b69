"""Self-collision on and off in the same run: stepping time, crossing edges and body depth.

N instances of a garment on the open body doing one library motion (``--shapes axis``: betas 1 =
0, 0.125, ...; ``--shapes bench``: bench_solver.py's shapes, instance 0 the mean shape, the
others' first four components uniform in [-2, 2]), with a preset's solver settings (default
thesis-tshirt; ``--preset none``: the solver's defaults), through
:func:`simgen.sim.simulate_batch` once without and once with self-contact (repulsion + impact
filter). Per run: wall time, the stepping time per output frame (first and last tenth of the
clip), output frames with crossing edges, the deepest regular vertex inside the body (also per
instance, and how many instances pass 1 and 3 mm) and the largest regular strain per instance (how
many pass the dataset check's 100%). ``--variants`` runs self-contact with other parameters too
(``thickness=3e-3,stiffness=1e5``: fields of SelfContactParams); ``--cg-iterations`` overrides the
preset's PCG cap. With ``--profile`` the first self-contact run is repeated without CUDA graphs
and every call is synchronised and timed: the impact filter's ms per substep and its rounds, by
quarter of the run, and how many substeps still had impacts after their last round.

    python scripts/bench_self_contact.py --device cuda:0 --garment tshirt --motion run -n 16 --frames 90 \\
        --profile --out sc.json
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import warp as wp

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_solver import commit, shape_batch  # noqa: E402


def shapes(kind: str, n: int, num_betas: int) -> np.ndarray:
    """(n, B) betas of the batch: 'axis' (beta 1 = 0, 0.125, ...) or 'bench' (bench_solver.py's)."""
    if kind == "bench":
        return shape_batch(n, num_betas)
    return np.array([[0.0, 0.125 * i] for i in range(n)])


def run(garment, body, motion, n, frames, cfg, kind="axis"):
    from simgen.sim import SimulationJob, simulate_batch

    jobs = [SimulationJob(motion, betas=b, frames=frames) for b in shapes(kind, n, body.num_betas)]
    t = time.perf_counter()
    results = simulate_batch(garment, body, jobs, cfg)
    wall = time.perf_counter() - t
    step = np.asarray(results[0].stats["step_time"], float)[1:] * 1e3   # output frame 0 takes no step
    tenth = max(1, len(step) // 10)
    crossing = np.concatenate([np.asarray(r.stats["crossing_edges"]) for r in results])
    depth = [round(1e3 * float(np.max(r.stats["max_depth_regular"])), 2) for r in results]
    strain = [round(float(np.max(r.stats["strain_max_regular"])), 3) for r in results]
    return {"depth_regular_mm_per_instance": depth,
            "instances_deeper_than_1_3_mm": [int(sum(d > 1.0 for d in depth)), int(sum(d > 3.0 for d in depth))],
            "strain_regular_max_per_instance": strain,
            "instances_strained_over_100_percent": int(sum(e > 1.0 for e in strain)),
            "wall_s": round(wall, 2), "step_ms_first_tenth": round(float(step[:tenth].mean()), 1),
            "step_ms_last_tenth": round(float(step[-tenth:].mean()), 1),
            "frames_with_crossings": int((crossing > 0).sum()), "frames": int(crossing.size),
            "max_crossing_edges": int(crossing.max()),
            "max_depth_regular_mm": max(depth)}


def profile(garment, body, motion, n, frames, cfg, kind="axis") -> dict:
    """The self-contact run without graphs, the impact filter timed per call (synchronised)."""
    from simgen.sim import impact_filter

    calls = []
    original = impact_filter.ImpactFilter.apply

    def timed(self, x0, state):
        wp.synchronize_device(self.model.device)
        t = time.perf_counter()
        original(self, x0, state)
        wp.synchronize_device(self.model.device)
        calls.append((time.perf_counter() - t, int(self._round.numpy()[0]), int(self.impacts.numpy().sum())))

    impact_filter.ImpactFilter.apply = timed
    try:
        run(garment, body, motion, n, frames, replace(cfg, cuda_graph=False), kind)
    finally:
        impact_filter.ImpactFilter.apply = original
    quarters = []
    for part in np.array_split(np.array(calls), 4):
        quarters.append({"filter_ms_per_substep": round(1e3 * float(part[:, 0].mean()), 2),
                         "rounds_histogram": np.bincount(part[:, 1].astype(int)).tolist(),
                         "substeps_with_impacts_left": int((part[:, 2] > 0).sum())})
    return {"substeps": len(calls), "quarters": quarters}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--device", default=None)
    p.add_argument("--preset", default="thesis-tshirt",
                   help="dataset preset whose solver settings are used ('none': the solver's defaults)")
    p.add_argument("--shapes", choices=("axis", "bench"), default="axis", help="the batch's betas (module doc)")
    p.add_argument("--garment", default="tshirt")
    p.add_argument("--motion", default="run")
    p.add_argument("-n", type=int, default=16, help="instances in the batch")
    p.add_argument("--frames", type=int, default=90)
    p.add_argument("--variants", nargs="*", default=[], help="more self-contact runs: FIELD=VALUE,... each")
    p.add_argument("--skip-none", action="store_true", help="no run without self-contact")
    p.add_argument("--cg-iterations", type=int, help="override the preset's PCG iterations per Newton iteration")
    p.add_argument("--profile", action="store_true", help="also time the filter per call, without CUDA graphs")
    p.add_argument("--out", type=Path)
    a = p.parse_args()
    wp.config.quiet = True
    from simgen.body import load as load_body
    from simgen.dataset import load_spec
    from simgen.garment import load_garment
    from simgen.motion import load_motion
    from simgen.params import SelfContactParams
    from simgen.sim import SimulationConfig

    cfg = SimulationConfig() if a.preset == "none" else load_spec(a.preset).solver_config()
    cfg = replace(cfg, device=a.device or cfg.device)
    if a.cg_iterations is not None:
        cfg = replace(cfg, solver=replace(cfg.solver, cg_iterations=a.cg_iterations))
    body = load_body("open")
    garment, motion = load_garment(a.garment, body=body), load_motion(a.motion)
    out = {"device": wp.get_device(cfg.device).name, "commit": commit(), "preset": a.preset, "garment": a.garment,
           "vertices": len(garment.vertices), "motion": a.motion, "instances": a.n, "frames": a.frames,
           "shapes": a.shapes, "betas": shapes(a.shapes, a.n, body.num_betas).tolist(),
           "cg_iterations": cfg.solver.cg_iterations, "runs": {}}
    runs = [] if a.skip_none else [("none", None)]
    runs.append(("self_contact", SelfContactParams()))
    for text in a.variants:
        fields = dict(item.split("=") for item in text.split(","))
        runs.append((f"self_contact {text}", SelfContactParams(**{k: type(getattr(SelfContactParams(), k))(float(v))
                                                                   for k, v in fields.items()})))
    for name, sc in runs:
        run_cfg = replace(cfg, solver=replace(cfg.solver, self_contact=sc))
        out["runs"][name] = run(garment, body, motion, a.n, a.frames, run_cfg, a.shapes)
        print(json.dumps({name: out["runs"][name]}), flush=True)
    if a.profile:
        sc_cfg = replace(cfg, solver=replace(cfg.solver, self_contact=SelfContactParams()))
        out["profile"] = profile(garment, body, motion, a.n, a.frames, sc_cfg, a.shapes)
        print(json.dumps({"profile": out["profile"]}), flush=True)
    if a.out:
        a.out.write_text(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
