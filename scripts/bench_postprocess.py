"""The collision post-processes of a predicted garment, timed, as JSON: the thesis's per-vertex push,
the push spread over the cloth (the models' default) and the metric post-process
(:class:`simgen.learn.relax.MetricRelax`), frame by frame (the runtime loop) and over a batch of
frames (an evaluation), with what each does to the mean triangle strain, the vertex distance and
the vertices inside the body.

The input stands in for a learned model's prediction: the garment's template skinned (LBS) on the
bundled body along a library clip, plus Gaussian noise of --noise [m] per vertex (a regression's
errors are a few mm). The times depend on the vertex count and the contacts, not on a model.

    python scripts/bench_postprocess.py --device cuda --garment tshirt --clip walk_fast --frames 60
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _record import commit  # noqa: E402


def prediction(garment_name: str, clip_name: str, frames: int, noise: float, device):
    """(noisy garment [m] (T, V, 3), posed body [m] (T, Vb, 3), garment, body model) on ``device``."""
    from simgen.body.torch_lbs import TorchBody
    from simgen.garment import load_garment
    from simgen.learn.data import body_for_identity
    from simgen.learn.skinning import lbs_torch
    from simgen.motion import load_motion

    garment, body = load_garment(garment_name), body_for_identity({})
    motion = load_motion(clip_name)
    n = min(frames, len(motion.poses))
    tb = TorchBody(body).to(device)
    betas = torch.zeros(n, tb.num_betas, device=device)
    poses = torch.as_tensor(motion.poses[:n], dtype=torch.float32, device=device)
    trans = torch.as_tensor(motion.trans[:n], dtype=torch.float32, device=device)
    with torch.no_grad():
        body_v, _, a = tb(betas, poses, trans)
        rest = torch.as_tensor(garment.vertices, dtype=torch.float32, device=device)
        weights = torch.as_tensor(garment.skin_weights, dtype=torch.float32, device=device)
        posed = lbs_torch(rest, weights, a)
    gen = torch.Generator(device="cpu").manual_seed(0)
    posed = posed + noise * torch.randn(posed.shape, generator=gen).to(device)
    return posed, body_v, garment, body


def timed(fn, frames: int, device, repeats: int) -> float:
    """Median milliseconds per frame of ``fn()`` (which handles ``frames`` frames), synchronised."""
    sync = torch.cuda.synchronize if torch.device(device).type == "cuda" else (lambda: None)
    fn()
    times = []
    for _ in range(repeats):
        sync()
        t0 = time.perf_counter()
        fn()
        sync()
        times.append((time.perf_counter() - t0) * 1e3 / frames)
    return float(np.median(times))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--device", default="cuda")
    ap.add_argument("--garment", default="tshirt")
    ap.add_argument("--clip", default="walk_fast")
    ap.add_argument("--frames", type=int, default=60, help="frames of the clip (the batch)")
    ap.add_argument("--single-frames", type=int, default=20, help="frames timed one by one")
    ap.add_argument("--noise", type=float, default=0.001, help="[m] Gaussian noise per vertex coordinate")
    ap.add_argument("--repeats", type=int, default=3, help="timed repeats of the batch")
    ap.add_argument("--out", type=Path, default=None, help="also write the JSON to this file")
    a = ap.parse_args()
    from simgen.learn.collision import CollisionSurface, MeshSpread, push_out
    from simgen.learn.evaluate import triangle_strain
    from simgen.learn.relax import MetricRelax
    from simgen.physics import ClothRest

    dev = torch.device(a.device)
    x, body_v, garment, body = prediction(a.garment, a.clip, a.frames, a.noise, dev)
    surface = CollisionSurface(body.faces, body.v_template, device=dev)
    spread = MeshSpread(garment.faces, garment.num_vertices).to(dev)
    t0 = time.perf_counter()
    relax = MetricRelax(garment.vertices, garment.faces, device=dev)
    build_s = time.perf_counter() - t0
    methods = {"push": lambda p, b: push_out(p, b, surface),
               "spread_push": lambda p, b: push_out(p, b, surface, spread=spread),
               "metric": lambda p, b: relax(p, b, surface, spread=spread)}
    rest = ClothRest.from_mesh(garment.vertices, garment.faces, "cotton", dtype=torch.float64)
    clean, _ = prediction(a.garment, a.clip, a.frames, 0.0, dev)[:2]

    def quality(points) -> dict:
        _, inside = push_out(points, body_v, surface, clearance=0.0)
        return {"mean_triangle_strain": float(triangle_strain(points.cpu(), rest).mean()),
                "mean_distance_to_lbs_mm": float((points - clean).norm(dim=-1).mean()) * 1e3,
                "inside_percent": 100.0 * float(inside.float().mean())}

    rows = {"input": quality(x)}
    n1 = min(a.single_frames, len(x))
    for name, fn in methods.items():
        out, _ = fn(x, body_v)
        rows[name] = {**quality(out),
                      "batch_ms_per_frame": timed(lambda fn=fn: fn(x, body_v), len(x), dev, a.repeats),
                      "single_ms_per_frame": timed(lambda fn=fn: [fn(x[k:k + 1], body_v[k:k + 1]) for k in range(n1)],
                                                   n1, dev, a.repeats)}
    text = json.dumps({"benchmark": "postprocess", "device": torch.cuda.get_device_name(dev) if dev.type == "cuda"
                       else "cpu", "threads": torch.get_num_threads(), "commit": commit(), "torch": torch.__version__,
                       "sizes": {"garment": a.garment, "vertices": garment.num_vertices,
                                 "triangles": len(garment.faces), "body_vertices": int(body_v.shape[1]),
                                 "frames": len(x), "single_frames": n1, "clip": a.clip, "noise_m": a.noise},
                       "strain_against": "the garment template's rest (the metric post-process's target)",
                       "metric_relax_build_s": build_s, "methods": rows}, indent=1)
    print(text)
    if a.out is not None:
        a.out.write_text(text + "\n")


if __name__ == "__main__":
    main()
