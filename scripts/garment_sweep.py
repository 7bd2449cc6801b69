"""Generate and check every garment's store of a multi-garment spec; prints (and saves) JSON.

    python scripts/garment_sweep.py --spec all-garments --out /tmp/ag --stride 5 --json ag.json
    python scripts/garment_sweep.py --spec all-garments-fast --out /tmp/agf --pack /tmp/packs \\
        --pack-sequences pants:squat__zero,skirt:walk_fast__zero

For each garment of the spec (one store each): sequences, cloth-frames simulated, wall time and
cloth-frames/s of its generation, then `simgen dataset check` on it (body penetration and the
placement measures on every ``stride``-th frame, strain on every frame): passed, the problems, the
least share of vertices on the body, the largest support drop below the skinned position, the
lowest vertex, the largest strain and the deepest regular vertex. ``--pack`` writes float16 packs
of chosen sequences (GARMENT:SEQUENCE) for `simgen dataset export` on another machine.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from dataset_bench import _commit, _device  # noqa: E402 - the same device and commit records


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--spec", default="all-garments", help="preset name or TOML spec")
    p.add_argument("--out", required=True, help="root folder of the stores (one sub-folder per garment)")
    p.add_argument("--device", help="override the spec's device (cpu, cuda, cuda:N)")
    p.add_argument("--garments", help="comma-separated subset of the spec's garments")
    p.add_argument("--motions", help="comma-separated subset of the spec's motions")
    p.add_argument("--max-frames", type=int, help="first N frames of each clip")
    p.add_argument("--stride", type=int, default=5, help="check the body on every stride-th frame")
    p.add_argument("--time-budget", type=float, help="seconds of generation (the next run resumes the stores)")
    p.add_argument("--pack", help="folder for float16 packs of --pack-sequences")
    p.add_argument("--pack-sequences", default="", help="GARMENT:SEQUENCE,... to pack")
    p.add_argument("--json", help="also write the JSON to this file")
    a = p.parse_args(argv)

    from simgen.dataset import check_dataset, generate_dataset, load_spec
    from simgen._warp_log import quiet_warp

    quiet_warp()
    spec = load_spec(a.spec).with_overrides(device=a.device, max_frames=a.max_frames,
                                            motions=a.motions.split(",") if a.motions else None)
    if a.garments:
        spec.garments = [g for g in spec.garments if g in a.garments.split(",")]
    device = spec.resolved_device()
    result = {"benchmark": "garment_sweep", "date": time.strftime("%Y-%m-%d"), "device": _device(device),
              "commit": _commit(), "spec": spec.name, "stride": a.stride, "garments": []}
    t0 = time.perf_counter()
    reports = generate_dataset(spec, a.out, time_budget=a.time_budget)
    result["generate_wall_s"] = time.perf_counter() - t0
    for r in reports:
        t1 = time.perf_counter()
        c = check_dataset(r.path, stride=a.stride, device=device)
        row = {"garment": r.garment, "store": r.path, "sequences": r.planned_sequences, "written_now": r.written,
               "stopped": r.stopped, "cloth_frames": r.cloth_frames, "wall_s": r.wall,
               "cloth_frames_per_s": r.cloth_frames_per_second, "retried_jobs": r.retried,
               "check_s": time.perf_counter() - t1, "passed": c.passed, "problems": c.problems[:10],
               "num_problems": len(c.problems)}
        row.update({k: v for k, v in c.to_dict().items()
                    if k in ("frames", "frames_checked_body", "max_depth", "max_strain", "max_strain_regular",
                             "pinched_strain_frames", "min_body_share", "max_support_drop", "min_height",
                              "crossing_frames", "max_crossing_edges")})
        row["sequences_with_crossings"] = len(c.to_dict().get("crossings", {}))
        result["garments"].append(row)
        print(json.dumps(row), flush=True)
    if a.pack:
        from simgen.dataset.export import pack_sequences

        wanted: dict = {}
        for item in filter(None, a.pack_sequences.split(",")):
            garment, seq = item.split(":")
            wanted.setdefault(garment, []).append(seq)
        Path(a.pack).mkdir(parents=True, exist_ok=True)
        for r in reports:
            if r.garment in wanted:
                pack_sequences(r.path, wanted[r.garment], Path(a.pack) / f"{spec.name}_{r.garment}.npz")
    text = json.dumps(result, indent=2)
    print(text)
    if a.json:
        Path(a.json).write_text(text + "\n")
    return 0 if all(g["passed"] for g in result["garments"]) else 1


if __name__ == "__main__":
    sys.exit(main())
