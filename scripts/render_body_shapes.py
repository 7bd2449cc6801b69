"""Picture and measurements of the body model's shape components.

Renders a grid (rows: betas 0..3, columns: beta = -2, 0, +2, front view, one shared camera so
sizes compare across the whole picture) and measures what one unit of each live component does:
height, volume and mass, waist circumference. Writes the PNG and a JSON of the measurements and
prints a table.

    python scripts/render_body_shapes.py                      # docs/img/body_betas.png, docs/body_betas.json
    python scripts/render_body_shapes.py --model my_smpl.npz --out my_smpl_betas.png --json my_smpl_betas.json

Measurements, on the rest (T-pose) body:
- height [m]: max y - min y.
- volume [l] of the closed skin (divergence theorem); mass [kg] at an assumed 1000 kg/m^3.
- waist circumference [m]: a tape measure round the narrowest part of the torso, i.e. the
  smallest convex-hull perimeter of horizontal sections between the pelvis and spine3 joints.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
BODY_DENSITY = 1000.0  # [kg/m^3] assumed for the mass column; human bodies are ~985-1060


def mesh_edges(faces: np.ndarray) -> np.ndarray:
    """Unique undirected edges (E, 2) of a triangle mesh."""
    edges = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    return np.unique(np.sort(edges, axis=1), axis=0)


def section_points(vertices: np.ndarray, edges: np.ndarray, y: float) -> np.ndarray:
    """Points [m] (K, 2) (x, z) where the mesh's edges (E, 2) cross the plane at height y [m]."""
    ya, yb = vertices[edges[:, 0], 1], vertices[edges[:, 1], 1]
    cross = (ya - y) * (yb - y) < 0
    a, b = vertices[edges[cross, 0]], vertices[edges[cross, 1]]
    t = ((y - a[:, 1]) / (b[:, 1] - a[:, 1]))[:, None]
    p = a + t * (b - a)
    return p[:, [0, 2]]


def tape_perimeter(points: np.ndarray) -> float:
    """Perimeter [m] of the convex hull of 2D points (K, 2): what a tape measure reads."""
    from scipy.spatial import ConvexHull

    return float(ConvexHull(points).area)  # in 2D, 'area' is the perimeter


def measure(model, betas: np.ndarray, edges: np.ndarray) -> dict:
    """Height [m], volume [l], mass [kg] and waist [m] of the rest body for betas (B,).

    edges: the model's unique edges (E, 2), see :func:`mesh_edges`.
    """
    from simgen.body.bake import signed_volume
    from simgen.body.model import SMPL_JOINT_NAMES

    v = model.shaped_vertices(betas)[0]
    joints = model.rest_joints(betas)[0]
    y_lo = joints[SMPL_JOINT_NAMES.index("pelvis"), 1]
    y_hi = joints[SMPL_JOINT_NAMES.index("spine3"), 1]
    waist = min(tape_perimeter(section_points(v, edges, y)) for y in np.linspace(y_lo, y_hi, 60))
    volume = signed_volume(v, model.faces)
    return {
        "height_m": float(np.ptp(v[:, 1])),
        "volume_l": volume * 1e3,
        "mass_kg": volume * BODY_DENSITY,
        "waist_m": waist,
    }


def render_grid(model, components: list[int], values: list[float], out: Path, cell: tuple[int, int]) -> None:
    """Render the grid PNG: one row per component, one column per value, shared camera."""
    from PIL import Image, ImageDraw, ImageFont

    from simgen.io.render import default_camera, render_frame

    spacing = 2.0  # [m] between bodies in a row; arm spans stay below ~1.95 m within -2..+2
    offsets = (np.arange(len(values)) - (len(values) - 1) / 2) * spacing
    rows = []
    for k in components:
        bodies = []
        for off, val in zip(offsets, values):
            b = np.zeros(model.num_betas)
            b[k] = val
            bodies.append(model.shaped_vertices(b)[0] + [off, 0.0, 0.0])
        rows.append(bodies)
    everything = np.concatenate([v for row in rows for v in row])
    bounds = np.stack([everything.min(axis=0), everything.max(axis=0)])
    bounds[0, 1] = 0.0
    width, height = cell[0] * len(values), cell[1]
    # A narrow field of view from straight ahead: nearly orthographic, so heights compare.
    camera = default_camera(bounds, aspect=width / height, azimuth=0.0, elevation=4.0, view_angle=12.0,
                            margin=0.04)
    tiles = []
    tmp = out.with_name(out.stem + ".row.png")
    try:
        for bodies in rows:
            render_frame(tmp, [(v, model.faces, "body") for v in bodies], camera=camera, size=(width, height))
            tiles.append(Image.open(tmp).convert("RGB"))
    finally:
        tmp.unlink(missing_ok=True)

    label_h = max(24, cell[1] // 14)
    font = ImageFont.load_default(size=int(label_h * 0.7))
    sheet = Image.new("RGB", (width, len(rows) * (height + label_h)), "white")
    draw = ImageDraw.Draw(sheet)
    for r, (k, tile) in enumerate(zip(components, tiles)):
        top = r * (height + label_h)
        sheet.paste(tile, (0, top + label_h))
        for c, val in enumerate(values):
            text = f"beta[{k}] = {val:+g}" if val else f"beta[{k}] = 0 (mean)"
            x = int((c + 0.5) * cell[0])
            draw.text((x, top + label_h // 2), text, fill="black", font=font, anchor="mm")
    out.parent.mkdir(parents=True, exist_ok=True)
    sheet.save(out, optimize=True)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--model", default="open", help="'open' (default) or a path to a body model file")
    parser.add_argument("--out", type=Path, default=REPO / "docs" / "img" / "body_betas.png")
    parser.add_argument("--json", type=Path, default=REPO / "docs" / "body_betas.json")
    parser.add_argument("--components", type=int, nargs="+", default=[0, 1, 2, 3])
    parser.add_argument("--values", type=float, nargs="+", default=[-2.0, 0.0, 2.0])
    parser.add_argument("--cell", type=int, nargs=2, default=[400, 400], metavar=("W", "H"),
                        help="pixel size of one body's cell")
    args = parser.parse_args(argv)

    from simgen.body import load

    model = load(args.model)
    bad = [k for k in args.components if not 0 <= k < model.num_betas]
    if bad:
        print(f"error: components {bad} are outside the model's {model.num_betas} betas", file=sys.stderr)
        return 2
    live = [k for k in range(model.num_betas) if np.any(model.shapedirs[:, :, k] != 0)]

    edges = mesh_edges(model.faces)
    mean = measure(model, np.zeros(model.num_betas), edges)
    components = []
    for k in live:
        at = {}
        for val in (-1.0, 1.0, -2.0, 2.0):
            b = np.zeros(model.num_betas)
            b[k] = val
            at[val] = measure(model, b, edges)
        per_unit = {key: (at[1.0][key] - at[-1.0][key]) / 2.0 for key in mean}
        components.append({"component": k, "per_unit_beta": per_unit, "at_minus_2": at[-2.0], "at_plus_2": at[2.0]})

    render_grid(model, args.components, args.values, args.out, tuple(args.cell))
    result = {
        "model": model.model_id,
        "density_kg_m3": BODY_DENSITY,
        "mean_shape": mean,
        "live_components": live,
        "components": components,
        "picture": str(args.out),
    }
    args.json.parent.mkdir(parents=True, exist_ok=True)
    args.json.write_text(json.dumps(result, indent=2) + "\n")

    print(f"{model.model_id}: mean shape height {mean['height_m']:.3f} m, volume {mean['volume_l']:.1f} l, "
          f"waist {mean['waist_m']:.3f} m")
    print("per unit beta    height [cm]   volume [l]   mass [kg]   waist [cm]")
    for c in components:
        d = c["per_unit_beta"]
        print(f"  beta[{c['component']}]        {100 * d['height_m']:+8.2f}   {d['volume_l']:+9.2f}   "
              f"{d['mass_kg']:+8.2f}   {100 * d['waist_m']:+9.2f}")
    print(f"wrote {args.out} and {args.json}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
