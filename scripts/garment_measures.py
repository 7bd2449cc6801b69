"""Size-chart measurements of the garment templates against the open body (issue 21, part 1).

Measures every template (tshirt, tank_top, dress, skirt, pants, shorts and their ``_1k`` variants)
the way a garment size chart states it, from the template mesh in the T-pose it was built in
(metres, y up, the body faces +z), and the matching body measurements of the open body in that
rest pose (``BodyModel.shaped_vertices``) at beta = 0 and at the presets' extreme shapes
beta 0 = +2 and -2. Every number is printed in centimetres.

How each measurement is taken (all girths are horizontal unless stated):

- garment girth at height y: the plane y cuts the triangles into segments, joined into loops;
  the girth is the length of the closed loop(s) enclosing the body's section centre (sleeves and
  the other leg are other loops); chest, waist and hip at the beta-0 body's heights, and the chest
  also 1 inch below the armhole (Gildan's definition; the underarm of the T-shirt, the lowest
  armhole point of the tank top and the dress);
- body girth: a tape measure, the convex-hull perimeter of the skin's section (arm points left
  out; per leg below the crotch); chest = largest torso girth between the natural waist and 1 cm
  under the armpit, hip = largest girth between the crotch and 5 cm (x height / 1.70 m) above the
  hip joints, waist = the natural waist of ``simgen.garment.envelope.body_landmarks``;
- garment body length: high point of the shoulder (HPS: the garment's highest point lateral of
  the neckline's side) down to the hem (mean height of the hem loop), vertical;
- sleeve length: along the garment's top outline seen from the front (the highest point of each
  plane x = const) from the centre back neck to the sleeve hem (Gildan's "centre back"
  definition), and from the shoulder joint's x to the sleeve hem; sleeve opening: length of the
  sleeve-hem loop, against the arm's girth in the same plane;
- bottoms: waistband = length of the waist loop; outseam / inseam = length of the outer / inner
  outline of the left leg seen from the front (the most / least lateral point of each horizontal
  section from the hem up to the waistband / the garment's crotch, the lowest cloth on the
  mid-sagittal plane); rise = waistband to crotch, vertical; thigh = girth 2.5 cm below the
  garment's crotch; leg opening = length of a hem loop; skirt length = waistband to hem,
  vertical; sweep = hem loop.

Shapes: the garment is one size (its cloth keeps the template's rest lengths while the start
protocol ramps the body to the target shape), so ease on a shape = the garment's girth minus that
shape's body girth; the waistband, tied to the body surface, is stretched to the shaped body's
girth along its attachment points.

    python scripts/garment_measures.py                 # JSON on stdout
    python scripts/garment_measures.py --out m.json    # and into a file
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import json
import sys
from collections import defaultdict
from pathlib import Path

import numpy as np

from _record import commit  # scripts/_record.py (the script's own folder is on sys.path)

REPO = Path(__file__).resolve().parents[1]
TEMPLATES = ("tshirt", "tank_top", "dress", "skirt", "pants", "shorts")
SHAPES = {"beta 0 = 0": 0.0, "beta 0 = +2": 2.0, "beta 0 = -2": -2.0}
TOPS = ("tshirt", "tank_top", "dress")
INCH = 0.0254  # [m]


# ----------------------------------------------------------------------------------- mesh sections
def _face_edges(faces) -> tuple[np.ndarray, np.ndarray]:
    """Unique undirected edges (E, 2) and each face's three edge ids (F, 3): (0 1), (1 2), (2 0)."""
    f = np.ascontiguousarray(faces, dtype=np.int64)
    return _face_edges_cached(f.tobytes(), len(f))


@functools.lru_cache(maxsize=8)
def _face_edges_cached(data: bytes, count: int) -> tuple[np.ndarray, np.ndarray]:
    f = np.frombuffer(data, dtype=np.int64).reshape(count, 3)
    e = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    edges, inverse = np.unique(np.sort(e, axis=1), axis=0, return_inverse=True)
    return edges, inverse.reshape(3, -1).T


def _chains(segments: np.ndarray) -> list[tuple[list[int], bool]]:
    """Join segments (S, 2) of node ids into chains: [(node ids in order, closed)]."""
    touching = defaultdict(list)
    for s, (a, b) in enumerate(segments.tolist()):
        touching[a].append(s)
        touching[b].append(s)
    used = np.zeros(len(segments), dtype=bool)
    ends = [n for n, ss in touching.items() if len(ss) == 1]
    starts = [(touching[n][0], n) for n in ends] + [(s, int(segments[s, 0])) for s in range(len(segments))]
    chains = []
    for s, node in starts:
        if used[s]:
            continue
        chain = [node]
        while True:
            used[s] = True
            a, b = segments[s]
            node = int(b if a == node else a)
            chain.append(node)
            free = [t for t in touching[node] if not used[t]]
            if not free:
                break
            s = free[0]
        closed = chain[0] == chain[-1]
        chains.append((chain[:-1] if closed else chain, closed))
    return chains


def plane_section(vertices, faces, value: float, axis: int = 1) -> list[tuple[np.ndarray, bool]]:
    """Polylines where the plane ``coordinate[axis] = value`` [m] cuts a triangle mesh.

    vertices [m] (V, 3), faces (F, 3). Returns [(points [m] (K, 3), closed)], one per connected
    piece of the section: closed loops, and open chains where the cut leaves the mesh through a
    boundary. A vertex lying exactly on the plane is handled by moving the plane by 1e-9 m.
    """
    v = np.asarray(vertices, dtype=np.float64)
    edges, face_edges = _face_edges(faces)
    while np.any(np.abs(v[:, axis] - value) < 1e-12):
        value += 1e-9
    side = v[:, axis] - value
    a, b = side[edges[:, 0]], side[edges[:, 1]]
    crossing = a * b < 0.0
    t = np.where(crossing, a / np.where(crossing, a - b, 1.0), 0.0)
    points = v[edges[:, 0]] + t[:, None] * (v[edges[:, 1]] - v[edges[:, 0]])
    hit = crossing[face_edges]
    cut = face_edges[hit.sum(axis=1) == 2]
    mask = crossing[cut]
    segments = cut[mask].reshape(-1, 2)
    return [(points[chain], closed) for chain, closed in _chains(segments)]


def polyline_length(points, closed: bool = True) -> float:
    """Length [m] of a polyline through points [m] (K, D) (closing it back to the start if ``closed``)."""
    p = np.asarray(points, dtype=np.float64)
    if len(p) < 2:
        return 0.0
    d = np.diff(np.concatenate([p, p[:1]]) if closed else p, axis=0)
    return float(np.linalg.norm(d, axis=1).sum())


def encloses(loop, centre, axes=(0, 2)) -> bool:
    """Whether the closed loop [m] (K, 3), projected on ``axes``, goes round ``centre`` [m] (2,) (even-odd rule)."""
    p = np.asarray(loop, dtype=np.float64)[:, list(axes)]
    q = np.roll(p, -1, axis=0)
    x, y = float(centre[0]), float(centre[1])
    straddle = (p[:, 1] > y) != (q[:, 1] > y)
    with np.errstate(divide="ignore", invalid="ignore"):
        x_cross = p[:, 0] + (y - p[:, 1]) * (q[:, 0] - p[:, 0]) / (q[:, 1] - p[:, 1])
    return bool(np.sum(straddle & (x_cross > x)) % 2 == 1)


def section_girth(vertices, faces, y: float, centre) -> float:
    """Girth [m] of a mesh at height y [m]: total length of the closed section loops that go round
    ``centre`` = (x, z) [m]; NaN where no loop does (the mesh does not reach y there)."""
    loops = [p for p, closed in plane_section(vertices, faces, y) if closed and encloses(p, centre)]
    return float(sum(polyline_length(p) for p in loops)) if loops else float("nan")


def hull_perimeter(points_2d) -> float:
    """Perimeter [m] of the convex hull of 2D points [m] (N, 2): a tape measure round them."""
    from scipy.spatial import ConvexHull, QhullError

    p = np.asarray(points_2d, dtype=np.float64)
    if len(p) < 3:
        return float("nan")
    try:
        return float(ConvexHull(p).area)  # in 2D qhull's "area" is the perimeter
    except QhullError:
        return float("nan")


def silhouette_length(vertices, faces, lo: float, hi: float, pick, axis: int = 1, step: float = 0.005,
                      dims=(0, 1)) -> float:
    """Length [m] of a silhouette line over a mesh: the polyline through ``pick(section points)`` of
    the sections by the planes coordinate[axis] = value for values from lo to hi [m] (every
    ``step`` [m], ends 0.5 mm inside), measured in the coordinates ``dims`` (default x, y: the
    outline seen from the front, so that a pick jumping front to back along a flat side adds
    nothing). ``pick``: points (K, 3) -> one point (3,) or None (skipped)."""
    values = np.linspace(lo + 5e-4, hi - 5e-4, max(2, int(np.ceil((hi - lo) / step)) + 1))
    picked = []
    for value in values:
        chains = plane_section(vertices, faces, float(value), axis=axis)
        if chains:
            p = pick(np.concatenate([c for c, _ in chains]))
            if p is not None:
                picked.append(p)
    if len(picked) < 2:
        return float("nan")
    return polyline_length(np.array(picked)[:, list(dims)], closed=False)


# ----------------------------------------------------------------------------------- the body
@dataclasses.dataclass
class BodyShape:
    """The open body in rest pose (T-pose) at one shape.

    model: a BodyModel whose template is the shaped rest body (betas 0 on it = this shape);
    vertices [m] (V, 3); lm: its :class:`simgen.garment.envelope.BodyLandmarks`; arm: per-vertex
    arm skinning weight (V,) (shoulders, elbows, wrists, hands); edges (E, 2) of the skin.
    """

    model: object
    vertices: np.ndarray
    lm: object
    arm: np.ndarray
    edges: np.ndarray

    @property
    def centre(self) -> np.ndarray:
        """(x, z) [m] of the torso's axis: the pelvis joint."""
        return self.lm.joints[0, [0, 2]]


def shaped_body(body, beta0: float) -> BodyShape:
    """The rest body at betas = (beta0, 0, ...), measured (landmarks as the garment recipes use them)."""
    from simgen.garment.envelope import body_edges, body_landmarks

    v = body.shaped_vertices(np.array([beta0]))[0]
    model = dataclasses.replace(body, v_template=v)
    arm = np.asarray(body.weights)[:, 16:24].sum(axis=1)
    return BodyShape(model=model, vertices=v, lm=body_landmarks(model), arm=arm, edges=body_edges(body.faces))


def _body_section(b: BodyShape, value: float, axis: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """Skin section points [m] (K, 3) by a plane and their arm weight (K,)."""
    from simgen.garment.envelope import horizontal_section

    pts, w = horizontal_section(b.vertices, b.edges, value, axis=axis, weights=b.arm[:, None])
    return pts, w[:, 0]


def torso_girth(b: BodyShape, y: float) -> float:
    """Tape-measure girth [m] of the body at height y [m], arms left out (both legs in one hull)."""
    pts, arm = _body_section(b, y)
    return hull_perimeter(pts[arm < 0.5][:, [0, 2]])


def leg_girth(b: BodyShape, y: float) -> float:
    """Tape-measure girth [m] of the left leg (x > centre) at height y [m] below the crotch."""
    pts, _ = _body_section(b, y)
    return hull_perimeter(pts[pts[:, 0] > b.lm.center_x][:, [0, 2]])


def arm_girth(b: BodyShape, x: float) -> float:
    """Tape-measure girth [m] of the arm in the plane x = const [m] (T-pose: across the arm)."""
    pts, _ = _body_section(b, x, axis=0)
    sh = b.lm.joint("left_shoulder" if x > b.lm.center_x else "right_shoulder")
    near = np.hypot(pts[:, 1] - sh[1], pts[:, 2] - sh[2]) < 0.15 * b.lm.scale
    return hull_perimeter(pts[near][:, [1, 2]])


def _argmax_height(fn, lo: float, hi: float, n: int = 60) -> tuple[float, float]:
    """(y, fn(y)) [m] of the largest fn over n heights in [lo, hi] [m]."""
    ys = np.linspace(lo, hi, n)
    vals = np.array([fn(float(y)) for y in ys])
    k = int(np.nanargmax(vals))
    return float(ys[k]), float(vals[k])


def body_hps_y(b: BodyShape) -> float:
    """Height [m] of the body's high point of the shoulder: the top of the skin 1-2 cm lateral of
    the neck's side, within 6 cm of the neck joint front to back."""
    lm, v = b.lm, b.vertices
    neck = lm.joint("neck")
    dx = np.abs(v[:, 0] - lm.center_x) - lm.neck_extent[0]
    sel = (dx > 0.01) & (dx < 0.02) & (np.abs(v[:, 2] - neck[2]) < 0.06) & (v[:, 1] < neck[1] + 0.05)
    return float(v[sel, 1].max())


def body_measures(b: BodyShape) -> dict:
    """Size-chart body measurements [m] of a shaped rest body (module doc): heights *_y and girths."""
    lm = b.lm
    s, armpit, hip_joint_y = lm.scale, float(lm.armpit_y.min()), float(lm.joints[[1, 2], 1].mean())
    chest_y, chest = _argmax_height(lambda y: torso_girth(b, y), lm.waist_y, armpit - 0.01)
    hip_y, hip = _argmax_height(lambda y: torso_girth(b, y), lm.crotch_y + 0.02 * s, hip_joint_y + 0.05 * s)
    _, thigh = _argmax_height(lambda y: leg_girth(b, y), lm.crotch_y - 0.08 * s, lm.crotch_y - 0.01, n=15)
    sh, el = lm.joint("left_shoulder"), lm.joint("left_elbow")
    return {
        "height": lm.height, "floor_y": lm.floor_y, "hps_y": body_hps_y(b), "armpit_y": armpit,
        "chest_y": chest_y, "chest": chest, "waist_y": lm.waist_y, "waist": torso_girth(b, lm.waist_y),
        "hip_y": hip_y, "hip": hip, "crotch_y": lm.crotch_y, "inside_leg": lm.crotch_y - lm.floor_y,
        "thigh": thigh, "knee_y": float(lm.joints[[4, 5], 1].mean()),
        "ankle_y": float(lm.joints[[7, 8], 1].mean()), "upper_arm_length": float(np.linalg.norm(el - sh)),
        "shoulder_x": float(sh[0] - lm.center_x),
    }


# ----------------------------------------------------------------------------------- the garments
def named_openings(garment) -> dict[str, np.ndarray]:
    """Opening name -> boundary loop vertex ids, matched to the metadata's opening centroids."""
    from simgen.garment.mesh import boundary_loops

    loops = boundary_loops(garment.faces)
    cent = np.array([garment.vertices[loop].mean(axis=0) for loop in loops])
    named = {}
    for op in garment.metadata["openings"]:
        k = int(np.argmin(np.linalg.norm(cent - np.asarray(op["centroid_m"]), axis=1)))
        named[op["name"]] = loops[k]
    if len({id(v) for v in named.values()}) != len(loops):
        raise RuntimeError(f"{garment.name}: openings do not match the boundary loops one to one")
    return named


def garment_hps_y(v: np.ndarray, neck: np.ndarray, cx: float) -> float:
    """Garment's high point of the shoulder [m]: its highest point at or lateral of the neckline's
    side (95 % of the neck loop's half width), i.e. where shoulder and neckline meet."""
    half = np.abs(v[neck, 0] - cx).max()
    return float(v[np.abs(v[:, 0] - cx) >= 0.95 * half, 1].max())


def underarm_y(v: np.ndarray, faces: np.ndarray, centre, y0: float, x_max: float, step: float = 0.002) -> float:
    """Garment's underarm height [m]: scanning up from y0 [m], the last height whose section loop
    round ``centre`` stays within |x - centre x| <= x_max [m] (above it the loop takes in the
    sleeves or the armholes open)."""
    y = y0
    while y < v[:, 1].max():
        loops = [p for p, closed in plane_section(v, faces, y + step) if closed and encloses(p, centre)]
        if not loops or np.abs(np.concatenate(loops)[:, 0] - centre[0]).max() > x_max:
            return y
        y += step
    return y


def _top_silhouette(v, faces, x0: float, x1: float) -> float:
    """Length [m] over the garment's top from x0 to x1 [m] (the highest point of each plane x)."""
    lo, hi = min(x0, x1), max(x0, x1)
    return silhouette_length(v, faces, lo, hi, lambda p: p[np.argmax(p[:, 1])], axis=0)


def _row(name: str, garment: float, body: dict | None = None, diff: dict | None = None, note: str = "") -> dict:
    """One measurement [cm]: the garment's value, the body's per shape, and garment minus body per
    shape (ease for girths) or what ``note`` says; NaN (the garment does not reach) becomes None."""
    def cm(x):
        return None if x is None or not np.isfinite(x) else round(100.0 * float(x), 1)

    body = body or {}
    if diff is None:
        diff = {k: garment - b for k, b in body.items()}
    return {"measure": name, "garment_cm": cm(garment), "body_cm": {k: cm(b) for k, b in body.items()},
            "diff_cm": {k: cm(d) for k, d in diff.items()}, "note": note}


def _girth_rows(v, faces, m0: dict, shapes: dict, names, centre) -> list[dict]:
    """Garment girths at the beta-0 body's landmark heights against each shape's body girth."""
    rows = []
    for key in names:
        g = section_girth(v, faces, m0[f"{key}_y"], centre)
        rows.append(_row(key, g, {s: m[key] for s, m in shapes.items()},
                         note=f"at the beta-0 body's {key} height {100 * m0[f'{key}_y']:.1f} cm; diff = ease"))
    return rows


def _hem_rows(length: float, hps_lift: float, shapes: dict, ref: str) -> list[dict]:
    """Where the hem of a garment hanging from the shoulders (HPS) lands on each shape: its height
    above the body's ``ref`` height (crotch_y, knee_y) [m], and the length in % of the body height."""
    hem = {s: m["hps_y"] + hps_lift - length - m[ref] for s, m in shapes.items()}
    share = {s: length / m["height"] for s, m in shapes.items()}
    return [_row(f"hem above {ref[:-2]}", float("nan"), {}, hem, note="hanging from the HPS; negative: below it"),
            _row("length / body height", float("nan"), {}, share, note="fraction x 100")]


def measure_top(garment, bodies: dict, shapes: dict) -> list[dict]:
    """Size-chart rows (see module doc) of a top or the dress against the bodies of every shape."""
    v, f = garment.vertices, garment.faces
    b0, m0 = bodies["beta 0 = 0"], shapes["beta 0 = 0"]
    cx, centre, s = b0.lm.center_x, b0.centre, b0.lm.scale
    op = named_openings(garment)
    hem_y = float(v[op["hem"], 1].mean())
    hps = garment_hps_y(v, op["neck"], cx)
    rows = _girth_rows(v, f, m0, shapes, ("chest", "waist", "hip"), centre)
    if "left_sleeve" in op:
        pts, arm = _body_section(b0, m0["chest_y"])
        half = np.abs(pts[arm < 0.5, 0] - cx).max()
        under = underarm_y(v, f, centre, m0["chest_y"], half + 0.05 * s)
    else:
        under = float(min(v[op["left_armhole"], 1].min(), v[op["right_armhole"], 1].min()))
    rows.append(_row("chest 1 inch below armhole", section_girth(v, f, under - INCH, centre),
                     {k: m["chest"] for k, m in shapes.items()}, note=f"garment underarm at {100 * under:.1f} cm"))
    rows.append(_row("hem sweep", polyline_length(v[op["hem"]]), {}))
    length = hps - hem_y
    rows.append(_row("body length (HPS to hem)", length, {k: m["hps_y"] - m["crotch_y"] for k, m in shapes.items()},
                     note="body: HPS to crotch; diff: garment minus that"))
    rows += _hem_rows(length, hps - m0["hps_y"], shapes, "knee_y" if garment.name.startswith("dress") else "crotch_y")
    if "left_sleeve" in op:
        rows += _sleeve_rows(garment, op["left_sleeve"], bodies, shapes)
    else:
        rows.append(_row("armhole", polyline_length(v[op["left_armhole"]]), {}))
    return rows


def _sleeve_rows(garment, sleeve: np.ndarray, bodies: dict, shapes: dict) -> list[dict]:
    """T-shirt sleeve: length (centre back and from the shoulder joint), reach along the upper arm,
    opening against the arm's girth where the hem sits on each shape (sleeve hung from the shoulder)."""
    v, f = garment.vertices, garment.faces
    m0, cx = shapes["beta 0 = 0"], bodies["beta 0 = 0"].lm.center_x
    x_end = float(v[sleeve[np.argmax(v[sleeve, 1])], 0])
    x_shoulder = cx + m0["shoulder_x"]
    from_shoulder = x_end - x_shoulder
    opening = polyline_length(v[sleeve])
    arm = {k: arm_girth(bodies[k], bodies[k].lm.center_x + m["shoulder_x"] + from_shoulder) for k, m in shapes.items()}
    return [
        _row("sleeve length, centre back", _top_silhouette(v, f, cx, x_end), {}),
        _row("sleeve length from shoulder joint", _top_silhouette(v, f, x_shoulder, x_end),
             {k: m["upper_arm_length"] for k, m in shapes.items()}, note="body: upper arm (shoulder to elbow joint)"),
        _row("sleeve reach / upper arm", float("nan"), {}, {k: from_shoulder / m["upper_arm_length"]
                                                           for k, m in shapes.items()}, note="fraction x 100"),
        _row("sleeve opening", opening, arm, note="body: arm girth where the sleeve hem sits; diff = ease"),
    ]


def band_on_shapes(garment, loop: np.ndarray, body, bodies: dict) -> dict:
    """The waistband on each shape: it is tied to the template body's surface points closest to its
    vertices, which move with the shape. Returns shape -> (girth [m] the band is stretched to:
    the attachment points' loop plus the band's own ease, its height [m], stretch ratio)."""
    from simgen.garment.skinning import closest_body_points

    v = garment.vertices[loop]
    pts = closest_body_points(v, body)
    corners = np.asarray(body.faces)[pts.face]
    on = {k: np.einsum("ak,akc->ac", pts.bary, b.vertices[corners]) for k, b in bodies.items()}
    base = on["beta 0 = 0"]
    ease, lift = polyline_length(v) - polyline_length(base), float(v[:, 1].mean() - base[:, 1].mean())
    return {k: (polyline_length(p) + ease, float(p[:, 1].mean()) + lift, polyline_length(p) / polyline_length(base))
            for k, p in on.items()}


def _left_leg_pick(cx: float, outer: bool):
    """Pick for :func:`silhouette_length`: the most (outer) or least lateral point with x > cx [m]."""
    def pick(p):
        left = p[p[:, 0] > cx]
        if len(left) == 0:
            return None
        return left[np.argmax(left[:, 0]) if outer else np.argmin(left[:, 0])]
    return pick


def _leg_rows(v, f, op, bodies: dict, band_y: float, band: dict, shapes: dict) -> list[dict]:
    """Pants and shorts: rise, outseam, inseam, thigh and leg opening (left leg). The garment's
    crotch is the lowest cloth on the mid-sagittal plane; ``band``: :func:`band_on_shapes`."""
    b0 = bodies["beta 0 = 0"]
    cx = b0.lm.center_x
    mid = np.concatenate([p for p, _ in plane_section(v, f, cx, axis=0)])
    crotch = float(mid[mid[:, 1] < band_y - 0.05, 1].min())
    hem_y = float(v[op["left_hem"], 1].mean())
    thigh_y = crotch - 0.025
    leg = _body_section(b0, thigh_y)[0]
    leg_centre = leg[leg[:, 0] > cx][:, [0, 2]].mean(axis=0)
    return [
        _row("rise (waistband to crotch)", band_y - crotch, {k: band[k][1] - m["crotch_y"] for k, m in shapes.items()},
             note="body: the attached band's height to the body's crotch; diff: garment crotch below the body's"),
        _row("outseam", silhouette_length(v, f, hem_y, band_y, _left_leg_pick(cx, outer=True)), {}),
        _row("inseam", silhouette_length(v, f, hem_y, crotch, _left_leg_pick(cx, outer=False)),
             {k: m["inside_leg"] for k, m in shapes.items()}, note="body: inside leg (crotch to floor)"),
        _row("thigh (2.5 cm below crotch)", section_girth(v, f, thigh_y, leg_centre),
             {k: leg_girth(bodies[k], m["crotch_y"] - 0.025) for k, m in shapes.items()},
             note="body: thigh girth 2.5 cm below its crotch; diff = ease"),
        _row("leg opening", polyline_length(v[op["left_hem"]]),
             {k: leg_girth(bodies[k], band[k][1] - (band_y - hem_y)) for k in shapes},
             note="body: leg girth where the hem hangs (band attached); diff = ease"),
    ]


def measure_bottom(garment, body, bodies: dict, shapes: dict) -> list[dict]:
    """Size-chart rows (see module doc) of skirt, pants or shorts against the bodies of every shape."""
    v, f = garment.vertices, garment.faces
    b0, m0 = bodies["beta 0 = 0"], shapes["beta 0 = 0"]
    op = named_openings(garment)
    band_y = float(v[op["waist"], 1].mean())
    band = band_on_shapes(garment, op["waist"], body, bodies)
    waist = polyline_length(v[op["waist"]])
    rows = [_row("waistband vs body at its height", waist, {"beta 0 = 0": torso_girth(b0, band_y)},
                 note=f"band at {100 * band_y:.1f} cm"),
            _row("waistband vs natural waist", waist, {k: m["waist"] for k, m in shapes.items()}),
            _row("band stretched to (attachment)", float("nan"), {k: b[0] for k, b in band.items()},
                 {k: b[2] - 1.0 for k, b in band.items()}, note="diff: band strain x 100 (%)")]
    rows += _girth_rows(v, f, m0, shapes, ("hip",), b0.centre)
    band_at = {k: b[1] for k, b in band.items()}  # [m] the band's height on each shape
    if "hem" in op:  # skirt
        hem_y = float(v[op["hem"], 1].mean())
        rows += [_row("skirt length", band_y - hem_y, {}), _row("hem sweep", polyline_length(v[op["hem"]]), {}),
                 _row("hem above knee", float("nan"), {}, {k: band_at[k] - (band_y - hem_y) - m["knee_y"]
                                                          for k, m in shapes.items()}, note="band on the body")]
        return rows
    rows += _leg_rows(v, f, op, bodies, band_y, band, shapes)
    hem_y = float(v[op["left_hem"], 1].mean())
    rows.append(_row("hem above ankle joint", float("nan"), {}, {k: band_at[k] - (band_y - hem_y) - m["ankle_y"]
                                                                 for k, m in shapes.items()}, note="band on the body"))
    return rows


# ----------------------------------------------------------------------------------- report
def measure_garment(name: str, body, bodies: dict, shapes: dict) -> list[dict]:
    """All rows of one template (``name`` with or without ``_1k``)."""
    from simgen.garment.library import load_garment

    garment = load_garment(name, body=body)
    if name.split("_1k")[0] in TOPS:
        return measure_top(garment, bodies, shapes)
    return measure_bottom(garment, body, bodies, shapes)


def variant_differences(full: list[dict], coarse: list[dict]) -> dict:
    """measure -> |full - 1k| [cm] of the garment values (rows with a garment value in both)."""
    out = {}
    for a, b in zip(full, coarse):
        if a["measure"] == b["measure"] and a["garment_cm"] is not None and b["garment_cm"] is not None:
            out[a["measure"]] = round(abs(a["garment_cm"] - b["garment_cm"]), 1)
    return out


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--garments", nargs="*", default=list(TEMPLATES), help="templates (their _1k variants too)")
    parser.add_argument("--out", type=Path, help="also write the JSON here")
    args = parser.parse_args(argv)
    from simgen import body as body_pkg

    body = body_pkg.load("open")
    bodies = {k: shaped_body(body, b) for k, b in SHAPES.items()}
    shapes = {k: body_measures(b) for k, b in bodies.items()}
    result = {"commit": commit(), "body": "open", "rest_pose": "T-pose (the templates' build pose)",
              "shapes": {k: {m: round(100 * x, 1) for m, x in v.items()} for k, v in shapes.items()},
              "units": "cm", "garments": {}, "variant_differences_cm": {}}
    for name in args.garments:
        for variant in (name, f"{name}_1k"):
            result["garments"][variant] = measure_garment(variant, body, bodies, shapes)
        result["variant_differences_cm"][name] = variant_differences(result["garments"][name],
                                                                     result["garments"][f"{name}_1k"])
    text = json.dumps(result, indent=1)
    print(text)
    if args.out:
        args.out.write_text(text + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
