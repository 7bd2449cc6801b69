"""SNUG training speed and the trained model's runtime and size, as JSON (BENCHMARKS.md).

Trains :func:`simgen.learn.snug.train_snug` on a garment for a time budget (fresh run, default
settings: thesis-tshirt physics, batch 16, the library's train clips), then rolls the model out on
a held-out clip, ``--repeats`` times after a warm-up, with and without the collision post-process.
Prints one JSON object: device, commit, seconds per epoch and the per-epoch losses from log.csv,
why training stopped, ms per frame of the rollouts, parameters and their float32 megabytes.

    python scripts/bench_snug.py --device cuda --garment tshirt --time-budget 240 --out runs/snug-bench
"""

from __future__ import annotations

import argparse
import csv
import json
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_solver import commit  # noqa: E402


def rollout_ms(model, clip, postprocess: bool, repeats: int, device: torch.device) -> float:
    """Mean ms per frame of ``repeats`` rollouts of the whole clip after one warm-up."""

    def sync():
        if device.type == "cuda":
            torch.cuda.synchronize(device)

    model.rollout(clip, postprocess=postprocess)
    sync()
    t = time.perf_counter()
    for _ in range(repeats):
        frames = model.rollout(clip, postprocess=postprocess).vertices.shape[0]
    sync()
    return 1e3 * (time.perf_counter() - t) / (repeats * frames)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--device", default="cuda")
    p.add_argument("--garment", default="tshirt")
    p.add_argument("--time-budget", type=float, default=240.0, help="[s] of training")
    p.add_argument("--clip", default="walk_fast", help="held-out clip of the runtime measurement")
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--out", type=Path, required=True, help="model folder (a fresh run: its snug/ is replaced)")
    a = p.parse_args()
    import warp as wp

    wp.config.quiet = True
    from simgen.learn.snug import load_snug_model, train_snug
    from simgen.motion import load_motion

    dev = torch.device(a.device)
    t = time.perf_counter()
    result = train_snug(a.garment, a.out, device=a.device, time_budget=a.time_budget, resume=False)
    wall = time.perf_counter() - t
    with open(result.folder / "log.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    seconds = [float(r["seconds"]) for r in rows]
    model = load_snug_model(result.folder, device=a.device)
    params = sum(q.numel() for q in model.net.parameters())
    clip = load_motion(a.clip)
    out = {"device": torch.cuda.get_device_name(dev) if dev.type == "cuda" else "cpu", "commit": commit(),
           "garment": a.garment, "time_budget_s": a.time_budget, "wall_s": round(wall, 1),
           "stopped": result.stopped, "epochs": result.epochs, "steps": result.steps,
           "seconds_per_epoch": round((seconds[-1] - seconds[0]) / max(1, len(seconds) - 1), 1)
           if len(seconds) > 1 else (seconds[0] if seconds else None),
           "epoch_loss": [round(float(r["loss"]), 4) for r in rows],
           "epoch_val_loss": [round(float(r["val_loss"]), 4) for r in rows if r["val_loss"]],
           "rollout_clip": a.clip,
           "ms_per_frame": round(rollout_ms(model, clip, False, a.repeats, dev), 3),
           "ms_per_frame_postprocess": round(rollout_ms(model, clip, True, a.repeats, dev), 3),
           "parameters": params, "megabytes_float32": round(params * 4 / 2**20, 2)}
    print(json.dumps(out), flush=True)


if __name__ == "__main__":
    main()
