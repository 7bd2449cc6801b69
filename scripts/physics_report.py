"""Physics report of simulated sequences against their LBS baselines (issue 6's done-criterion).

For every simulated .npz (``SimulationResult.save_npz`` / ``simgen simulate``; also the files of
scripts/sim_library.py) this evaluates the SNUG terms per frame of the simulation and of its LBS
baseline (the garment skinned with its weights, same body), and the incremental potential of eq. 5.4
per frame (h = 1/fps, the prediction 2 x_{t-1} - x_{t-2} from the simulated previous frames) of the
simulated frame and of the LBS frame. It prints one JSON line per file and writes OUT (JSON) with the
per-term means of both, the share of frames where the simulated frame's potential is lower, and the
totals pooled over every frame of every file; with --plots DIR also the per-frame figures.

    python scripts/physics_report.py runs/tshirt_walk_fast.npz runs/tshirt_dance.npz --out physics_report.json
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
import time
from pathlib import Path

import numpy as np

from _record import commit  # scripts/_record.py (the script's own folder is on sys.path)


def report_file(path: Path, *, contact: str, device: str, plots: Path | None, body,
                bending_rest: str = "template") -> dict:
    """The report entry of one simulated sequence (see the module doc)."""
    import torch

    from simgen.physics import BodySurface, ContactParams, compare_potentials, evaluate_sequence, load_simulation

    t0 = time.perf_counter()
    sim = load_simulation(path, body=body)
    lbs = sim.lbs()
    surface = BodySurface.from_body(sim.body, device=device)
    rest = sim.rest(device=torch.device(device), bending_rest=bending_rest)
    params = ContactParams.snug() if contact == "snug" else sim.contact
    reports = [evaluate_sequence(s.positions, s.body_vertices, rest, surface, s.fps, contact_params=params,
                                 root=s.root, name=s.name, device=device) for s in (sim, lbs)]
    snug = [evaluate_sequence(s.positions, s.body_vertices, rest, surface, s.fps, contact_params=params,
                              root=s.root, name=s.name, device=device, normalisation="snug") for s in (sim, lbs)]
    cmp = compare_potentials(sim.positions, lbs.positions, sim.body_vertices, rest, surface, sim.fps,
                             contact_params=params, device=device)
    if plots is not None:
        from simgen.physics.plot import have_matplotlib, plot_potentials, plot_terms

        if have_matplotlib():
            plot_terms(reports, plots / f"{path.stem}_terms.png", title=f"{path.stem}: simulated vs LBS")
            plot_potentials(cmp, plots / f"{path.stem}_potential.png", fps=sim.fps, title=path.stem)
        else:
            print("note: matplotlib is not installed, no plots (the JSON has every number)", file=sys.stderr)
    means = {which: rep.means() for which, rep in zip(("simulated", "lbs"), reports)}
    for which, rep in zip(("simulated", "lbs"), snug):
        means[which]["gravity_root"] = rep.means()["gravity"]
    return {
        "file": str(path), "garment": sim.meta["garment"], "motion": sim.meta["motion"], "frames": sim.num_frames,
        "fps": sim.fps, "vertices": rest.num_vertices, "garment_mass_kg": rest.total_mass,
        "garment_area_m2": rest.total_area, "material": rest.material.name,
        "contact": {"margin": params.margin, "stiffness": params.stiffness, "power": params.power},
        "bending_rest": bending_rest,
        "means": means,
        "potential": {"frames_compared": int(len(cmp["frames"])), "simulated_lower_share": cmp["lower_share"],
                      "simulated_mean": float(np.mean(cmp["reference"])), "lbs_mean": float(np.mean(cmp["candidate"])),
                      "simulated_lower": int(np.sum(cmp["reference"] < cmp["candidate"])),
                      "terms_simulated": {k: float(np.mean(v)) for k, v in cmp["reference_terms"].items()},
                      "terms_lbs": {k: float(np.mean(v)) for k, v in cmp["candidate_terms"].items()}},
        "seconds": time.perf_counter() - t0,
    }


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("files", nargs="+", type=Path, help="simulated .npz files")
    parser.add_argument("--out", type=Path, default=Path("physics_report.json"), help="JSON report to write")
    parser.add_argument("--contact", choices=("solver", "snug"), default="solver",
                        help="collision term: the parameters each file was simulated with, or SNUG's (k = 250 J/m^3)")
    parser.add_argument("--bending-rest", choices=("template", "flat"), default="template",
                        help="bending rest angle: the solver's (template) or SNUG's (flat)")
    parser.add_argument("--device", default="cpu", help="torch device (cpu, cuda)")
    parser.add_argument("--body", default="open", help="body model (default: the bundled open body)")
    parser.add_argument("--plots", type=Path, default=None, help="folder for per-file PNG figures")
    args = parser.parse_args(argv)

    from simgen import body as body_pkg
    from simgen._fileio import atomic_write_bytes
    from simgen.errors import InputError

    try:
        body = body_pkg.load(args.body)
        entries = []
        for path in args.files:
            entry = report_file(path, contact=args.contact, device=args.device, plots=args.plots, body=body,
                                bending_rest=args.bending_rest)
            print(json.dumps(entry), flush=True)
            entries.append(entry)
    except InputError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    compared = sum(e["potential"]["frames_compared"] for e in entries)
    lower = sum(e["potential"]["simulated_lower"] for e in entries)
    weights = np.array([e["frames"] for e in entries], dtype=np.float64)

    def pooled(which: str, key: str) -> float:
        return float(np.average([e["means"][which][key] for e in entries], weights=weights))

    keys = ("strain", "bending", "gravity", "gravity_root", "inertia", "collision", "inside_share")
    doc = {
        "device": args.device, "host": platform.node(), "commit": commit(),
        "date": time.strftime("%Y-%m-%d"), "contact": args.contact,
        "files": entries,
        "pooled": {
            "frames": int(weights.sum()), "frames_compared": compared,
            "simulated_lower_share": lower / compared if compared else float("nan"),
            "means_simulated": {k: pooled("simulated", k) for k in keys},
            "means_lbs": {k: pooled("lbs", k) for k in keys},
        },
        "units": "J per frame (sum over the garment, mean over frames); inside_share: fraction of vertices; "
                 "gravity from the floor, gravity_root from the root joint",
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_bytes(args.out, (json.dumps(doc, indent=2) + "\n").encode("utf-8"))
    print(json.dumps({"pooled": doc["pooled"], "out": str(args.out)}), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
