"""What a generation pool's start-up is made of: Warp's import and init, loading the preset's body
and garment, then building a :class:`simgen.sim.SimulationPool` of ``--slots`` slots under cProfile.

The pool's build (model, solver, body and collider, frame statistics) is what every generator
process does before its first frame, with and without Ray (BENCHMARKS.md, the start-up entries).
Kernel loads count where they happen; run it twice on a fresh machine to time a warm kernel cache.

    python scripts/bench_pool_build.py --device cuda:0 --slots 128 --out build.json

Prints (and writes with --out) JSON with the device, commit and sizes, the three times [s] and the
``--top`` functions by cumulative time inside the build.
"""

from __future__ import annotations

import argparse
import cProfile
import io
import pstats
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from dataset_bench import _commit, _device, _emit  # noqa: E402  (scripts/ sibling: records and output)


def _top(profile: cProfile.Profile, n: int) -> list[dict]:
    """The n entries with the largest cumulative time: {function, calls, cumulative_s, own_s}."""
    stats = pstats.Stats(profile, stream=io.StringIO())
    rows = []
    for (path, line, name), (_, calls, own, cumulative, _) in stats.stats.items():
        rows.append({"function": f"{Path(path).name}:{line}({name})", "calls": calls,
                     "cumulative_s": cumulative, "own_s": own})
    return sorted(rows, key=lambda r: -r["cumulative_s"])[:n]


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--spec", default="thesis-tshirt", help="dataset preset whose solver, garment and body to use")
    p.add_argument("--device", default=None)
    p.add_argument("--slots", type=int, default=128)
    p.add_argument("--top", type=int, default=20, help="profile entries to report")
    p.add_argument("--out", type=Path, default=None)
    a = p.parse_args(argv)

    t0 = time.perf_counter()
    import warp as wp

    from simgen._warp_log import quiet_warp

    quiet_warp()
    wp.init()
    t1 = time.perf_counter()
    from simgen.dataset import load_spec
    from simgen.dataset.execute import _load_body, _load_garment
    from simgen.sim import SimulationPool

    spec = load_spec(a.spec).with_overrides(device=a.device)
    body = _load_body(spec.body)
    garment = _load_garment(spec.garments[0], spec.body)
    config = spec.solver_config()
    t2 = time.perf_counter()
    profile = cProfile.Profile()
    profile.enable()
    pool = SimulationPool(garment, body, a.slots, config, fps=spec.fps)
    wp.synchronize_device(config.device)
    profile.disable()
    t3 = time.perf_counter()
    result = {"benchmark": "pool_build", "date": time.strftime("%Y-%m-%d"),
              "device": _device(spec.resolved_device()), "commit": _commit(), "spec": spec.name,
              "sizes": {"garment": garment.name, "vertices": int(len(garment.vertices)), "slots": pool.num_slots},
              "warp_import_init_s": t1 - t0, "load_s": t2 - t1, "pool_build_s": t3 - t2,
              "profile_top": _top(profile, a.top)}
    _emit(result, a.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
