"""The garments as a user sees them (issue 21, part 5): simulate on the GPU machine, render on the CPU one.

``simulate`` (needs only Warp): every garment after the start protocol on the open body at beta = 0
and at beta 0 = +2 and -2, in the walk's pose at 1 s (mid-stride, arms down; the clip itself starts
in a T-pose), and four frames of the
T-shirt in walk, jumping_jacks and cmu_131_03_hop and of the dress in jumping_jacks and dance at
beta = 0, each with its default material and the solver's defaults. Writes one .npz per picture
(cloth and body positions [m], float32, faces) and prints one JSON line each.

``render`` (VTK): each .npz as a 1280x720 JPEG in docs/img: the rests front and side with the
three shapes side by side, the clips' four frames side by side (each frame moved to the origin).

    python scripts/garment_gallery.py simulate --device cuda:0 --out gallery/
    python scripts/garment_gallery.py render gallery/ --out docs/img
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

GARMENTS = ("tshirt", "tank_top", "dress", "skirt", "pants", "shorts")
SHAPES = {"beta 0 = 0": [0.0], "beta 0 = +2": [2.0], "beta 0 = -2": [-2.0]}
CLIPS = (("tshirt", "walk"), ("tshirt", "jumping_jacks"), ("tshirt", "cmu_131_03_hop"),
         ("dress", "jumping_jacks"), ("dress", "dance"))
SIZE = (1280, 720)


def simulate_all(device: str, out: Path, only: list[str] | None = None) -> None:
    """Run every picture's simulation (module doc), or those named in ``only`` (rest_tshirt,
    tshirt_walk, ...), and save it under ``out``."""
    from simgen import body as body_pkg
    from simgen.garment.library import load_garment
    from simgen.motion.library import load_motion
    from simgen.motion.ops import trim
    from simgen.sim import SimulationConfig, SimulationJob, simulate_batch

    body = body_pkg.load("open")
    cfg = SimulationConfig(record_body=True, device=device)
    out.mkdir(parents=True, exist_ok=True)
    for name in GARMENTS:
        if only and f"rest_{name}" not in only:
            continue
        garment, clip = load_garment(name, body=body), trim(load_motion("walk"), 1.0, 1.5)
        t = time.perf_counter()
        jobs = [SimulationJob(clip, np.array(b), frames=1) for b in SHAPES.values()]
        results = simulate_batch(garment, body, jobs, cfg)
        _save(out / f"rest_{name}.npz", results, [0] * len(results), body, labels=list(SHAPES))
        print(json.dumps({"picture": f"rest_{name}", "seconds": round(time.perf_counter() - t, 1)}))
    for name, motion in CLIPS:
        if only and f"{name}_{motion}" not in only:
            continue
        garment, clip = load_garment(name, body=body), load_motion(motion)
        t = time.perf_counter()
        (result,) = simulate_batch(garment, body, [SimulationJob(clip, np.zeros(1))], cfg)
        frames = np.linspace(0, result.num_frames - 1, 4).round().astype(int).tolist()
        _save(out / f"{name}_{motion}.npz", [result] * 4, frames, body,
              labels=[f"frame {k} ({k / result.fps:.1f} s)" for k in frames])
        print(json.dumps({"picture": f"{name}_{motion}", "frames": frames,
                          "crossing_frames": int((result.stats["crossing_edges"] > 0).sum()),
                          "seconds": round(time.perf_counter() - t, 1)}))


def _save(path: Path, results, frames, body, labels) -> None:
    """One picture's panels: cloth (P, V, 3) and body (P, Vb, 3) [m] float32, faces, labels."""
    for r in results:
        if not hasattr(r, "positions"):
            raise RuntimeError(f"{path.stem}: a simulation failed: {r}")
    np.savez_compressed(
        path, cloth=np.stack([r.positions[k] for r, k in zip(results, frames)]).astype(np.float32),
        body=np.stack([r.body_vertices[k] for r, k in zip(results, frames)]).astype(np.float32),
        faces=results[0].faces, body_faces=np.asarray(body.faces), labels=np.array(labels))


def render_all(data: Path, out: Path) -> None:
    """Render every .npz of ``data`` into ``out`` as JPEG (module doc)."""
    for path in sorted(data.glob("*.npz")):
        with np.load(path) as d:
            cloth, body, faces, body_faces = d["cloth"], d["body"], d["faces"], d["body_faces"]
            labels = [str(s) for s in d["labels"]]
        if path.stem.startswith("rest_"):
            name = path.stem[len("rest_"):]
            for view, azimuth, axis in (("front", 0.0, (0.75, 0.0, 0.0)), ("side", 90.0, (0.0, 0.0, -0.75))):
                _render(out / f"garment_rest_{name}_{view}.jpg", cloth, body, faces, body_faces, labels,
                        azimuth, axis, title=f"{name} after the start protocol ({view})")
        else:
            _render(out / f"sim_{path.stem}.jpg", cloth, body, faces, body_faces, labels, 20.0, (0.75, 0.0, 0.0),
                    title=path.stem.replace("_", " ", 1))
        print(path.stem)


def _render(path: Path, cloth, body, faces, body_faces, labels, azimuth: float, step, title: str) -> None:
    """Panels side by side, panel k moved by k ``step`` [m] (3,) after centring its body on the
    vertical axis, in one picture from ``azimuth`` [deg], written as a JPEG."""
    import tempfile

    from PIL import Image

    from simgen.io.render import default_camera, render_frame

    meshes, boxes = [], []
    for k in range(len(cloth)):
        shift = -body[k].mean(axis=0)
        shift[1] = 0.0
        shift += k * np.asarray(step)
        meshes += [(body[k] + shift, body_faces, "body"), (cloth[k] + shift, faces, "garment")]
        boxes.append(np.vstack([body[k] + shift, cloth[k] + shift]))
    points = np.vstack(boxes)
    camera = default_camera(np.stack([points.min(0), points.max(0)]), aspect=SIZE[0] / SIZE[1],
                            azimuth=azimuth, elevation=8.0)
    caption = f"{title}\nleft to right: {', '.join(labels)}"
    with tempfile.TemporaryDirectory() as tmp:
        png = render_frame(Path(tmp) / "p.png", meshes, camera=camera, size=SIZE, title=caption)
        path.parent.mkdir(parents=True, exist_ok=True)
        Image.open(png).convert("RGB").save(path, quality=82)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    sub = p.add_subparsers(dest="cmd", required=True)
    s = sub.add_parser("simulate")
    s.add_argument("--device", default="cuda:0")
    s.add_argument("--out", type=Path, required=True)
    s.add_argument("--only", nargs="+", default=None, metavar="PICTURE",
                   help="just these pictures: rest_<garment> or <garment>_<motion> (default: all)")
    r = sub.add_parser("render")
    r.add_argument("data", type=Path)
    r.add_argument("--out", type=Path, default=Path("docs/img"))
    a = p.parse_args()
    if a.cmd == "simulate":
        known = [f"rest_{g}" for g in GARMENTS] + [f"{g}_{m}" for g, m in CLIPS]
        unknown = sorted(set(a.only or []) - set(known))
        if unknown:
            p.error(f"--only: unknown picture(s) {', '.join(unknown)}; known: {', '.join(known)}")
        simulate_all(a.device, a.out, a.only)
    else:
        render_all(a.data, a.out)


if __name__ == "__main__":
    main()
