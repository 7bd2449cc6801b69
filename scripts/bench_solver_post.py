"""The solver post-process at several substep counts, on a trained model's held-out predictions, as
JSON: per setting, its cost (ms per frame, frames stepped again or left raw) and what it leaves
against the simulation on the same frames (strain energy and the other ``simgen.physics`` terms,
mean triangle strain, mean vertex error, vertices inside the body).

The raw predictions (fit + wrinkle, no post-process) of ``--sequences`` held-out sequences (spread
over the split's first test group), each cut to ``--frames`` frames, go through
:class:`simgen.learn.solver_post.SolverPostProcess` once per ``--substeps`` value (all spanning
``--duration``, by default the post-process's), each a fresh
post-process with the store's material and solver settings, run once untimed (kernel builds, the
solver of each chunk size) before the timed pass.

    python scripts/bench_solver_post.py --store simgen-thesis/dataset --model simgen-thesis/model_motion \\
        --device cuda --substeps 2 5 10 20
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _record import commit  # noqa: E402


def held_out(available, split, count: int) -> list[str]:
    """``count`` of the ``available`` sequence ids in the split's first test group, spread over its
    motions and shapes."""
    group = next(iter(split.test.values()))
    ids = sorted(set(group) & set(available))
    if not ids:
        raise SystemExit("the store holds none of the model's held-out sequences")
    picks = np.unique(np.linspace(0, len(ids) - 1, min(count, len(ids))).round().astype(int))
    return [ids[k] for k in picks]


def inside_share(points: np.ndarray, body_vertices: np.ndarray, counter, stride: int) -> float:
    """Share of the vertices [m] (T, V, 3) inside the posed body [m] (T, Vb, 3), every ``stride``-th
    frame, counted as ``simgen dataset check`` counts its regular vertices (``counter``, an
    :class:`simgen.learn.comparison.metrics.InsideCounter`; until 2026-11-29 every vertex inside by
    the winding number counted, those at body self-intersections too)."""
    return float(np.mean([counter.fractions({"x": points[k]}, body_vertices[k])["x"]
                          for k in range(0, len(points), stride)]))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--store", type=Path, required=True, help="the dataset store the model was trained on")
    ap.add_argument("--model", type=Path, required=True, help="a trained model folder (template, fit, wrinkle)")
    ap.add_argument("--device", default="cuda")
    ap.add_argument("--substeps", type=int, nargs="+", default=[2, 5, 10, 20])
    ap.add_argument("--duration", type=float, default=None,
                    help="simulated time per frame [s] (default: the post-process's); the substeps share it")
    ap.add_argument("--chunk", type=int, default=128, help="frames stepped together")
    ap.add_argument("--sequences", type=int, default=8)
    ap.add_argument("--frames", type=int, default=120, help="frames per sequence (from the first)")
    ap.add_argument("--inside-stride", type=int, default=5)
    args = ap.parse_args()

    from simgen.dataset import open_dataset
    from simgen.learn.data import body_for_identity, load_garment_data
    from simgen.learn.comparison.metrics import InsideCounter
    from simgen.learn.evaluate import cloth_rest, physics_terms, triangle_strain
    from simgen.learn.garment_model import load_garment_model, load_split
    from simgen.learn.solver_post import SolverPostProcess

    dev = torch.device(args.device)
    warp_device = "cuda:0" if dev.type == "cuda" else "cpu"
    split = load_split(args.model)
    if split is None:
        raise SystemExit(f"{args.model} holds no split.json")
    ids = held_out(open_dataset(args.store).sequence_ids(), split, args.sequences)
    data = load_garment_data(args.store, sequence_ids=ids, max_frames=args.frames)
    identity = {"garment": dict(data.identity.get("garment", {})), "body": dict(data.identity.get("body", {}))}
    model = load_garment_model(args.model, identity=identity, device=dev)
    body = body_for_identity(data.identity)
    counter = InsideCounter(body, data.skin_weights, data.attrs.get("solver"), warp_device)
    rest = cloth_rest(data)

    runs = []
    with torch.no_grad():
        for sid in ids:
            s = data.sequences[sid]
            b, p, t = (torch.as_tensor(a, dtype=torch.float32, device=dev) for a in (s.betas, s.poses, s.trans))
            raw = model.predict(b, p, t, s.fps, postprocess=False).raw
            runs.append({"id": sid, "fps": s.fps, "raw": raw, "body": model.body(b, p, t)[0], "gt": s.vertices})

    def score(name: str, sets: list[np.ndarray]) -> dict:
        phys = physics_terms(data, [{"fps": r["fps"], "body_vertices": r["body"].cpu().numpy(), "sets": {name: x}}
                                    for r, x in zip(runs, sets)], body, dev)[name]
        err = np.concatenate([100.0 * np.linalg.norm(x - r["gt"], axis=-1).mean(-1) for r, x in zip(runs, sets)])
        return {"physics_J_per_frame": phys,
                "triangle_strain": float(np.mean(np.concatenate([triangle_strain(x, rest) for x in sets]))),
                "error_cm": float(err.mean()),
                "inside_share": float(np.mean([inside_share(x, r["body"].cpu().numpy(), counter, args.inside_stride)
                                               for r, x in zip(runs, sets)]))}

    rows = {"simulation": score("ground_truth", [r["gt"] for r in runs]),
            "raw": score("model_raw", [r["raw"].cpu().numpy() for r in runs])}
    for substeps in args.substeps:
        post = SolverPostProcess.from_data(data, body, substeps=substeps, chunk=args.chunk, device=warp_device,
                                           **({} if args.duration is None else {"duration": args.duration}))
        for r in runs:       # untimed: kernel builds and the solver of every chunk size the runs need
            for s in range(0, len(r["raw"]), args.chunk):
                post(r["raw"][s:s + args.chunk], r["body"][s:s + args.chunk])
        post.reset_counters()
        outs = [post(r["raw"], r["body"]).cpu().numpy() for r in runs]
        rows[f"solver_{substeps}"] = {**score("model_solver", outs), **post.report()}
        print(json.dumps({"substeps": substeps, **post.report()}), file=sys.stderr, flush=True)

    sim = rows["simulation"]["physics_J_per_frame"]["strain"]
    for row in rows.values():
        row["strain_energy_vs_simulation"] = row["physics_J_per_frame"]["strain"] / max(sim, 1e-30)
    frames = int(sum(len(r["raw"]) for r in runs))
    print(json.dumps({"benchmark": "solver_post", "commit": commit(), "device": args.device,
                      "gpu": torch.cuda.get_device_name() if dev.type == "cuda" else None,
                      "sizes": {"sequences": ids, "frames": frames, "vertices": int(runs[0]["raw"].shape[1]),
                                "chunk": args.chunk},
                      "rows": rows}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
