"""Time a soft-tissue store's generation (issue 25's target: the `softtissue` preset in at most 8
minutes on one H100); prints (and saves) JSON with device, commit and sizes.

    python scripts/softtissue_bench.py --spec softtissue --device cuda:0 --out st-store --time-budget 500
    python scripts/softtissue_bench.py --spec my_small.toml --device cpu        # a temporary store

A fresh store is generated (or an existing one resumed with --out): wall time, stored frames per
second (every stored frame of every shape), the simulation's share, and the projection of the
preset's whole plan from the frames done when a budget stopped the run.
"""

from __future__ import annotations

import argparse
import shutil
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from dataset_bench import _commit, _device, _emit  # noqa: E402  (one definition of what a benchmark records)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--spec", default="softtissue", help="soft-tissue preset or TOML spec (default: softtissue)")
    p.add_argument("--out", help="store folder (default: a temporary folder, removed afterwards)")
    p.add_argument("--device", help="override the spec's device (cpu, cuda:N)")
    p.add_argument("--max-sequences", type=int)
    p.add_argument("--time-budget", type=float, help="seconds")
    p.add_argument("--json", help="also write the JSON to this file")
    a = p.parse_args(argv)

    from simgen._warp_log import quiet_warp
    from simgen.dataset.softtissue import (check_softtissue_store, generate_softtissue, load_softtissue_spec,
                                           planned_frames)

    quiet_warp()
    spec = load_softtissue_spec(a.spec)
    if a.device:
        spec = replace(spec, device=a.device)
    device = spec.resolved_device()
    info = _device(device)
    tmp = tempfile.mkdtemp(prefix="simgen-stbench-") if a.out is None else None
    out = a.out or str(Path(tmp) / "store")
    try:
        t0 = time.perf_counter()

        def progress(done, total):
            print(f"[{time.perf_counter() - t0:7.1f} s] {done}/{total} sequences", file=sys.stderr, flush=True)

        r = generate_softtissue(spec, out, max_sequences=a.max_sequences, time_budget=a.time_budget,
                                progress=progress)
        wall = time.perf_counter() - t0
        check = check_softtissue_store(out)
        planned = planned_frames(spec)
        rate = r.frames / r.wall if r.wall > 0 else None
        result = {
            "benchmark": "softtissue_generate", "date": time.strftime("%Y-%m-%d"), "device": info,
            "commit": _commit(), "spec": spec.name,
            "sizes": {"shapes": len(spec.shapes), "motions": len(spec.motions), "mirror": spec.mirror,
                      "planned_sequences": r.planned, "planned_frames": planned,
                      "sequences_done": check["sequences"], "sequences_written_now": r.written,
                      "rate_hz": spec.flesh.rate, "fps": spec.flesh.fps, "batch_size": spec.batch_size},
            "frames": r.frames, "wall_s": r.wall, "run_wall_s": wall, "simulate_s": r.simulate_wall,
            "frames_per_s": rate, "stopped": r.stopped,
            "projected_preset_s": planned / rate if rate else None,
            "check": {k: check[k] for k in ("passed", "problems", "max_peak_m", "min_det", "mean_speed_mps")},
        }
    finally:
        if tmp is not None:
            shutil.rmtree(tmp, ignore_errors=True)
    _emit(result, a.json)
    return 0


if __name__ == "__main__":
    sys.exit(main())
