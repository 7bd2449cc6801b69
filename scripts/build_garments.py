"""Rebuild the bundled garment templates, their pictures and the table of docs/garments.md.

For every template (tshirt, tank_top, dress, skirt, pants, shorts) on the bundled open body:
builds the default size into garments/NAME/ and the ~1k-triangle variant into garments/NAME_1k/
(simgen.garment.build.build_garment: generate, skin, check, save), renders
docs/img/garment_NAME.png (front and back, the garment coloured by the dominant skinning joint of
each vertex, with a legend) and docs/img/garment_variants_1k.png (the 1k variants), writes
docs/garments.json (counts and quality numbers) and replaces the table between the markers of
docs/garments.md.

    python scripts/build_garments.py                 # everything
    python scripts/build_garments.py --only skirt    # one template (table rows of the others kept)
    python scripts/build_garments.py --no-build      # pictures and table from the saved garments
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
SIZES = {"": None, "_1k": 1000}  # name suffix -> target_triangles
TABLE_START = "<!-- garment-table:start -->"
TABLE_END = "<!-- garment-table:end -->"

# One colour per SMPL joint (RGB in [0, 1]); left and right of a pair differ, neighbours contrast.
JOINT_COLORS = np.array([
    [0.55, 0.55, 0.58], [0.90, 0.60, 0.10], [0.20, 0.55, 0.85], [0.60, 0.40, 0.75],  # pelvis, hips, spine1
    [0.95, 0.80, 0.25], [0.35, 0.75, 0.90], [0.45, 0.70, 0.35],                      # knees, spine2
    [0.80, 0.45, 0.20], [0.15, 0.35, 0.65], [0.85, 0.35, 0.45],                      # ankles, spine3
    [0.60, 0.30, 0.10], [0.10, 0.25, 0.45], [0.95, 0.55, 0.70],                      # feet, neck
    [0.75, 0.20, 0.20], [0.20, 0.45, 0.30], [0.98, 0.90, 0.80],                      # collars, head
    [0.95, 0.40, 0.30], [0.30, 0.80, 0.55], [0.70, 0.15, 0.35], [0.15, 0.55, 0.50],  # shoulders, elbows
    [0.50, 0.10, 0.25], [0.10, 0.40, 0.35], [0.35, 0.05, 0.15], [0.05, 0.25, 0.20],  # wrists, hands
])


def dominant_colors(weights: np.ndarray) -> tuple[np.ndarray, list[int]]:
    """Per-vertex colours (V, 3) of the dominant joint and the joints that dominate somewhere."""
    dom = weights.argmax(axis=1)
    return JOINT_COLORS[dom], sorted(set(dom.tolist()))


def render_garment(garment, body, path: Path, title: str) -> None:
    """Front and back views side by side with a legend of the dominant joints."""
    from PIL import Image, ImageDraw

    from simgen.body import SMPL_JOINT_NAMES
    from simgen.io.render import default_camera, render_frame

    colors, joints = dominant_colors(garment.skin_weights)
    lo, hi = garment.vertices.min(axis=0), garment.vertices.max(axis=0)
    pad = 0.08
    bounds = np.stack([lo - pad, hi + pad])
    cell = (640, 720)
    views = []
    for azimuth, label in ((25.0, "front"), (205.0, "back")):
        cam = default_camera(bounds, aspect=cell[0] / cell[1], azimuth=azimuth, elevation=10.0, margin=0.04)
        tmp = path.with_name(f".{path.stem}_{label}.png")
        render_frame(tmp, [(body.v_template, body.faces, "body"), (garment.vertices, garment.faces, colors)],
                     camera=cam, size=cell, title=f"{title} ({label})" if label == "front" else label)
        views.append(Image.open(tmp).convert("RGB"))
        tmp.unlink()
    legend_h = 28 * ((len(joints) + 3) // 4) + 12
    out = Image.new("RGB", (2 * cell[0], cell[1] + legend_h), (255, 255, 255))
    out.paste(views[0], (0, 0))
    out.paste(views[1], (cell[0], 0))
    draw = ImageDraw.Draw(out)
    for k, j in enumerate(joints):
        x = 16 + (k % 4) * (2 * cell[0] - 32) // 4
        y = cell[1] + 8 + 28 * (k // 4)
        rgb = tuple(int(round(255 * c)) for c in JOINT_COLORS[j])
        draw.rectangle([x, y + 2, x + 18, y + 20], fill=rgb, outline=(60, 60, 60))
        draw.text((x + 26, y + 5), SMPL_JOINT_NAMES[j], fill=(30, 30, 30))
    out.save(path, optimize=True)


def render_variants(garments: list, body, path: Path) -> None:
    """The 1k variants in a 3 x 2 grid of front views (uniform garment colour, mesh visible)."""
    from PIL import Image

    from simgen.io.render import default_camera, render_frame

    cell = (400, 440)
    grid = Image.new("RGB", (3 * cell[0], 2 * cell[1]), (255, 255, 255))
    for k, g in enumerate(garments):
        lo, hi = g.vertices.min(axis=0), g.vertices.max(axis=0)
        cam = default_camera(np.stack([lo - 0.06, hi + 0.06]), aspect=cell[0] / cell[1], azimuth=25.0,
                             elevation=10.0, margin=0.04)
        tmp = path.with_name(f".{path.stem}_{k}.png")
        colors, _ = dominant_colors(g.skin_weights)
        render_frame(tmp, [(body.v_template, body.faces, "body"), (g.vertices, g.faces, colors)], camera=cam,
                     size=cell, title=f"{g.name}: {g.num_triangles} tri")
        grid.paste(Image.open(tmp).convert("RGB"), ((k % 3) * cell[0], (k // 3) * cell[1]))
        tmp.unlink()
    grid.save(path, optimize=True)


def summary(garment) -> dict:
    """The numbers of the docs table, read from the garment's quality report."""
    q = {item["name"]: item for item in garment.metadata["quality"]["items"]}
    cov = {k: v for k, v in q.items() if k.startswith("coverage") or k == "hem_clear_of_legs"}
    parts = []
    for name, item in cov.items():
        vals = item["values"]
        if name == "coverage_sleeves":
            parts.append("sleeves end at {:.2f} of shoulder-elbow".format(min(vals["reach"].values())))
        elif name == "coverage_no_sleeves":
            parts.append("no sleeves: arm reach {:.2f}".format(max(vals["reach"].values())))
        elif name == "coverage_hem" and "hem_max_y_m" in vals and "waist_y_m" in vals:
            parts.append("hem top {:.3f} m < waist {:.3f} m".format(vals["hem_max_y_m"], vals["waist_y_m"]))
        elif name == "coverage_hem" and "knee_y_m" in vals and "hem_max_y_m" in vals:
            parts.append("hem top {:.3f} m < knees {:.3f} m".format(vals["hem_max_y_m"], vals["knee_y_m"]))
        elif name == "coverage_hem" and "hem_min_y_m" in vals:
            parts.append("hem bottom {:.3f} m > knees {:.3f} m".format(vals["hem_min_y_m"], vals["knee_y_m"]))
        elif name == "coverage_waist":
            parts.append("waistband {:.3f} m".format(vals["waist_mean_y_m"]))
        elif name == "coverage_hems" and "hem_mean_y_m" in vals:
            parts.append("leg hems {:.3f} m".format(np.mean(list(vals["hem_mean_y_m"].values()))))
        elif name == "coverage_hems":
            parts.append("leg hems {:.3f}-{:.3f} m".format(min(vals["hem_min_y_m"].values()),
                                                            max(vals["hem_max_y_m"].values())))
        elif name == "hem_clear_of_legs":
            parts.append("hem {:.1f} cm clear of legs".format(100 * vals["min_hem_distance_m"]))
    regions = q["ease"]["values"]["regions"]
    tight = [k for k, r in regions.items() if r["fit"] == "tight"]
    loose = [k for k, r in regions.items() if r["fit"] == "loose"]
    spread = q["edge_spread"]["values"]
    return {
        "name": garment.name,
        "template": garment.metadata["template"],
        "vertices": garment.num_vertices,
        "triangles": garment.num_triangles,
        "openings": [o["name"] for o in garment.metadata["openings"]],
        "min_angle_deg": q["min_angle"]["values"]["min_angle_deg"],
        "edge_mm": [1e3 * spread["p1_m"], 1e3 * spread["p50_m"], 1e3 * spread["p99_m"]],
        "edge_max_over_min": spread["max_over_min"],
        "clearance_mm": 1e3 * q["clearance"]["values"]["min_signed_distance_m"],
        "ease_max_cm": 100 * q["ease"]["values"]["max_m"],
        "tight": tight,
        "loose": loose,
        "coverage": "; ".join(parts),
        "skinning": garment.metadata["skinning"]["method"],
        "material": garment.metadata["default_material"],
        "passed": garment.metadata["quality"]["passed"],
        "build_seconds": garment.metadata.get("build_seconds"),
    }


def table(rows: list[dict]) -> str:
    lines = [
        "| garment | vertices | triangles | openings | min angle | edges p1/p50/p99 (max/min) | clearance | "
        "ease: tight / loose regions (max) | coverage | skinning, material | build | check |",
        "|---|---:|---:|---|---:|---|---:|---|---|---|---:|---|",
    ]
    for r in rows:
        p1, p50, p99 = r["edge_mm"]
        ease = f"{', '.join(r['tight']) or '-'} / {', '.join(r['loose']) or '-'} ({r['ease_max_cm']:.1f} cm)"
        seconds = "" if r.get("build_seconds") is None else f"{r['build_seconds']:.0f} s"
        lines.append(
            f"| {r['name']} | {r['vertices']:,} | {r['triangles']:,} "
            f"| {len(r['openings'])}: {', '.join(r['openings'])} "
            f"| {r['min_angle_deg']:.1f} deg | {p1:.1f}/{p50:.1f}/{p99:.1f} mm ({r['edge_max_over_min']:.2f}) "
            f"| {r['clearance_mm']:.1f} mm | {ease} | {r['coverage']} | {r['skinning']}, {r['material']} "
            f"| {seconds} | {'pass' if r['passed'] else 'FAIL'} |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--only", nargs="*", help="templates to rebuild (default: all)")
    parser.add_argument("--no-build", action="store_true", help="use the saved garments")
    parser.add_argument("--no-render", action="store_true", help="skip the pictures")
    parser.add_argument("--garments", type=Path, default=REPO / "garments")
    parser.add_argument("--docs", type=Path, default=REPO / "docs")
    args = parser.parse_args(argv)

    import simgen.body
    from simgen.garment.build import build_garment
    from simgen.garment.garment import Garment
    from simgen.garment.templates import TEMPLATE_NAMES

    body = simgen.body.load("open")
    names = args.only or list(TEMPLATE_NAMES)
    rows_path = args.docs / "garments.json"
    rows = {r["name"]: r for r in json.loads(rows_path.read_text())} if rows_path.is_file() else {}
    img = args.docs / "img"
    img.mkdir(parents=True, exist_ok=True)
    for name in names:
        for suffix, target in SIZES.items():
            if args.no_build:
                garment = Garment.load(args.garments / f"{name}{suffix}")
                seconds = rows.get(garment.name, {}).get("build_seconds")
            else:
                t0 = time.perf_counter()
                garment = build_garment(name, body, target_triangles=target, out_dir=args.garments)
                seconds = round(time.perf_counter() - t0, 1)
            garment.metadata["build_seconds"] = seconds
            rows[garment.name] = summary(garment)
            print(f"{garment.name:12s} {garment.num_vertices:6d} v {garment.num_triangles:6d} tri  "
                  f"{rows[garment.name]['coverage']}  ({seconds} s)", flush=True)
            if not args.no_render and not suffix:
                render_garment(garment, body, img / f"garment_{name}.png",
                               f"{name}: {garment.num_triangles} triangles, {garment.metadata['skinning']['method']}")
    if not args.no_render:
        variants = [Garment.load(args.garments / f"{n}_1k") for n in TEMPLATE_NAMES
                    if (args.garments / f"{n}_1k").is_dir()]
        if variants:
            render_variants(variants, body, img / "garment_variants_1k.png")
    order = [f"{n}{s}" for s in SIZES for n in TEMPLATE_NAMES]
    ordered = [rows[k] for k in order if k in rows]
    rows_path.write_text(json.dumps(ordered, indent=1) + "\n")
    doc = args.docs / "garments.md"
    if doc.is_file():
        text = doc.read_text()
        if TABLE_START in text and TABLE_END in text:
            head, rest = text.split(TABLE_START, 1)
            _, tail = rest.split(TABLE_END, 1)
            doc.write_text(f"{head}{TABLE_START}\n{table(ordered)}\n{TABLE_END}{tail}")
    print(table(ordered))
    return 0


if __name__ == "__main__":
    sys.exit(main())
