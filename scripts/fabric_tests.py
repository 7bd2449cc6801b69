"""Standard fabric tests on the cloth solver (issue 21): ASTM D1388 cantilever and Cusick drape.

For each material preset this runs :func:`simgen.sim.fabric_tests.cantilever_bending_length`
(bending length c_sim from the 41.5 deg overhang against c_pred = (B / (rho g))^(1/3), and Peirce's
formula at the measured angle; with the library's thin clamp row and, for comparison, a regular
one) and :func:`simgen.sim.fabric_tests.cusick_drape` (drape coefficient and nodes, one drape per
mesh seed: the folds, and with them DC, depend on where the asymmetry starts them) on finer meshes
than tests/test_fabric_tests.py, and prints one JSON object with the device, the git commit, the
mesh sizes and the numbers (progress goes to stderr); --out also writes it to a file. No published
drape range is checked (see the module doc of simgen.sim.fabric_tests).

    python scripts/fabric_tests.py
    python scripts/fabric_tests.py --materials interlock,cotton --drape-spacing 0.005 --out fabric_tests.json
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
import time
from pathlib import Path

from _record import commit  # scripts/_record.py (the script's own folder is on sys.path)


def _rounded(value, digits: int = 6):
    """value with every float rounded to ``digits`` significant digits (nested dicts and lists too)."""
    if isinstance(value, float):
        return float(f"{value:.{digits}g}")
    if isinstance(value, dict):
        return {k: _rounded(v, digits) for k, v in value.items()}
    if isinstance(value, list):
        return [_rounded(v, digits) for v in value]
    return value


def run_material(name: str, *, rows: int, drape_spacing: float, seeds: list[int], device: str) -> dict:
    """The report entry of one material: its parameters, the cantilever (thin clamp row, and a
    regular one for comparison) and the drape of each seed's mesh with their mean."""
    import numpy as np

    from simgen.materials import get_material
    from simgen.sim.fabric_tests import cantilever_bending_length, cusick_drape

    material = get_material(name)
    params = {k: v for k, v in material.to_dict().items() if k != "source"}
    params.update(flexural_rigidity=material.flexural_rigidity, stretch_stiffness_2d=material.stretch_stiffness_2d)
    cantilever = cantilever_bending_length(material, rows=rows, device=device)
    regular = cantilever_bending_length(material, rows=rows, clamp_gap=1.0, device=device)
    print(f"{name}: cantilever c_sim {cantilever['c_sim'] * 1e3:.2f} mm / c_pred {cantilever['c_pred'] * 1e3:.2f} mm "
          f"= {cantilever['ratio']:.3f} (regular clamp row {regular['ratio']:.3f}; "
          f"{cantilever['seconds'] + regular['seconds']:.0f} s)", file=sys.stderr, flush=True)
    drapes = [cusick_drape(material, spacing=drape_spacing, seed=seed, device=device) for seed in seeds]
    dc = np.array([d["drape_coefficient"] for d in drapes])
    print(f"{name}: drape DC {dc.mean():.3f} (seeds {', '.join(f'{x:.3f}' for x in dc)}), nodes "
          f"{[d['nodes'] for d in drapes]} ({sum(d['seconds'] for d in drapes):.0f} s)", file=sys.stderr, flush=True)
    summary = {"drape_coefficient_mean": float(dc.mean()), "drape_coefficient_min": float(dc.min()),
               "drape_coefficient_max": float(dc.max()), "nodes": [d["nodes"] for d in drapes]}
    return {"material": params, "cantilever": cantilever, "cantilever_regular_clamp_row": regular,
            "drape": summary, "drape_runs": drapes}


def _names_and_seeds(materials: str, seeds: str) -> tuple[list[str], list[int]]:
    """The --materials names and --seeds integers, or InputError naming the bad option."""
    from simgen.errors import InputError

    names = [n.strip() for n in materials.split(",") if n.strip()]
    try:
        numbers = [int(x) for x in seeds.split(",") if x.strip()]
    except ValueError:
        raise InputError(f"--seeds must be comma-separated integers, got {seeds!r}") from None
    if not names or not numbers:
        raise InputError(f"--materials and --seeds must each name at least one, got {materials!r} and {seeds!r}")
    return names, numbers


def _document(args, seeds: list[int], results: dict, seconds: float) -> dict:
    """The JSON report: where and on what it ran, the settings, and the per-material results."""
    import warp as wp

    return {
        "device": str(wp.get_device(args.device)), "host": platform.node(), "commit": commit(),
        "date": time.strftime("%Y-%m-%d"), "warp": wp.config.version,
        "settings": {"cantilever_rows": args.cantilever_rows, "cantilever_width_m": 0.025,
                     "drape_spacing_m": args.drape_spacing, "drape_seeds": seeds, "shadow_pixel_m": 1.0e-3,
                     "cantilever_clamp_gap": 0.1, "drape_clamp_gap": 0.1},
        "published_drape_range": None,
        "results": _rounded(results),
        "units": "lengths m, areas m^2, angles deg, seconds wall time; ratio = c_sim / c_pred; residual: unbalanced "
                 "force / weight of the free cloth",
        "seconds": round(seconds, 1),
    }


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--materials", default="interlock,cotton,denim,silk",
                        help="comma-separated material presets (default: interlock,cotton,denim,silk)")
    parser.add_argument("--cantilever-rows", type=int, default=24,
                        help="rows of cells over the cantilever's overhang (the tests use 13-15)")
    parser.add_argument("--drape-spacing", type=float, default=0.0075,
                        help="[m] the drape disc's mesh spacing (the tests use 0.0125)")
    parser.add_argument("--seeds", default="0,1,2",
                        help="comma-separated seeds of the drape meshes' asymmetry (one drape per seed)")
    parser.add_argument("--device", default="cpu", help="Warp device (cpu, cuda:0)")
    parser.add_argument("--out", type=Path, default=None, help="also write the JSON report here")
    args = parser.parse_args(argv)

    from simgen._fileio import atomic_write_bytes
    from simgen._warp_log import init_warp
    from simgen.errors import InputError

    init_warp(args.device)  # no banner, no module lines, no CUDA-driver warning on the CPU
    t0 = time.perf_counter()
    try:
        names, seeds = _names_and_seeds(args.materials, args.seeds)
        results = {n: run_material(n, rows=args.cantilever_rows, drape_spacing=args.drape_spacing, seeds=seeds,
                                   device=args.device) for n in names}
    except InputError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    text = json.dumps(_document(args, seeds, results, time.perf_counter() - t0), indent=2)
    print(text, flush=True)
    if args.out is not None:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        atomic_write_bytes(args.out, (text + "\n").encode("utf-8"))
    return 0


if __name__ == "__main__":
    sys.exit(main())
