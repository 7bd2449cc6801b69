"""The six garment templates, generated from code on any SMPL-format body in rest pose.

    from simgen.garment.templates import generate_template
    vertices, faces, info = generate_template("tshirt", simgen.body.load("open"))

Method (see :mod:`simgen.garment.envelope` and :mod:`simgen.garment.remesh`):

1. Landmarks are measured on the rest body: joints, natural waist, crotch, armpits, neck
   (:func:`simgen.garment.envelope.body_landmarks`). Every length below scales with the body.
2. An *envelope* is contoured around the body: the iso-surface at distance ``ease(p)`` from the
   body, or from the body united with horizontal convex hulls of its sections (tops below the
   armpits; skirt and dress over both legs, so they bridge the gap between the legs and hang clear
   of them; pants and shorts over each leg). The ease is a per-template profile over height, tight
   at the shoulders and the waistband, looser towards hems, with a separate profile along the arms.
3. The openings are level sets of smooth "keep" functions built from the landmarks: horizontal
   planes for hems and waistbands, a plane across the arm for sleeves, a tilted paraboloid bowl for
   the neckline (fitted through a front, a back and a side point), and a rounded corner for
   armholes. The curves are inserted into the envelope as feature edges, the closed envelope is
   remeshed to uniform triangles at the target edge length (Botsch-Kobbelt, gpytoolbox), and the
   triangles outside are removed: the openings come out as smooth, evenly sampled loops.
4. Where an opening turns sharply at a coarse edge length the cut is tidied (ears removed, long
   and short boundary edges split or collapsed, boundary vertices put back on the curve at even
   spacing), and Delaunay flips, short-edge collapses and tangential smoothing on the envelope
   (openings fixed) fix thin triangles. Vertices closer than 2 mm + a 3 mm margin to the body are
   pushed out to that distance.

The target edge length is found from the envelope area and ``target_triangles``; one or two
remeshing passes bring the triangle count within a few percent of the target.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from simgen.errors import InputError
from simgen.garment.envelope import BodyLandmarks, HullSpec, body_edges, body_landmarks, horizontal_section, smoothstep

__all__ = [
    "TEMPLATE_NAMES",
    "EXPECTED_OPENINGS",
    "DEFAULT_TRIANGLES",
    "DEFAULT_MATERIALS",
    "DEFAULT_SKINNING",
    "CLEARANCE",
    "CLEARANCE_MARGIN",
    "GENERATOR_VERSION",
    "Opening",
    "TemplateRecipe",
    "generate_template",
    "template_recipe",
]

TEMPLATE_NAMES = ("tshirt", "tank_top", "dress", "skirt", "pants", "shorts")

#: Boundary loops of each template: tshirt (neck, hem, two sleeves), tank_top (neck, hem, two
#: armholes), dress (neck, two armholes, hem), skirt (waistband, hem), pants and shorts (waistband,
#: two leg hems).
EXPECTED_OPENINGS = {"tshirt": 4, "tank_top": 4, "dress": 4, "skirt": 2, "pants": 3, "shorts": 3}

#: Triangle count of the full-size templates (tshirt: the thesis T-shirt has 8,710).
DEFAULT_TRIANGLES = {"tshirt": 8710, "tank_top": 6000, "dress": 16000, "skirt": 5000, "pants": 10000,
                     "shorts": 6000}

#: Default material preset of each template (simgen.materials; the T-shirt takes the measured set's T-shirt
#: knit, gray-interlock, as the thesis's ch. 4 dataset does).
DEFAULT_MATERIALS = {"tshirt": "interlock", "tank_top": "interlock", "dress": "silk", "skirt": "cotton",
                     "pants": "denim", "shorts": "cotton"}

#: Default skinning method. Tops use the thesis's closest-triangle weights (ch. 4). Everything around
#: the legs uses diffused weights (thesis eq. 6.4): a skirt or dress bridges the legs, and at the
#: crotch seam of pants and shorts closest-triangle weights jump between the legs (LBS of the walk
#: stretched a pants edge 9x with closest weights, 2.2x with diffused ones).
DEFAULT_SKINNING = {"tshirt": "closest", "tank_top": "closest", "dress": "diffused", "skirt": "diffused",
                    "pants": "diffused", "shorts": "diffused"}

CLEARANCE = 0.002  # [m] every vertex at least this far outside the template body (the contract)
CLEARANCE_MARGIN = 0.003  # [m] added by the generator, so the contract holds with room to spare
GENERATOR_VERSION = 2

# Rough surface area [m^2] of each template on a 1.70 m body: chooses the contouring grid before
# the real area is known (it only sets the grid spacing, not the result's size).
_AREA_HINT = {"tshirt": 0.67, "tank_top": 0.46, "dress": 1.1, "skirt": 0.52, "pants": 0.98, "shorts": 0.41}


@dataclass(frozen=True)
class Opening:
    """One boundary loop of a template: where the cloth ends.

    name: "neck", "hem", "left_sleeve", ...; keep: the keep function whose zero set it is
    (positive on the cloth), points [m] (N, 3) -> (N,); side: "left" (x > center), "right" or
    None, to tell apart two loops of one function (the two leg hems of pants).
    """

    name: str
    keep: Callable[[np.ndarray], np.ndarray]
    side: str | None = None


@dataclass
class TemplateRecipe:
    """Everything :func:`generate_template` needs for one template on one body.

    box [m], shape (2, 3): contouring region (min and max corner); ease: points [m] (N, 3) -> ease
    [m] (N,); hull: the horizontal hulls joining the cover; openings: one :class:`Opening` per
    boundary loop; parameters: the recipe's numbers [m], recorded in the garment's metadata.
    """

    box: np.ndarray  # [m] (2, 3) contouring region
    ease: Callable[[np.ndarray], np.ndarray]
    hull: HullSpec | None
    openings: list[Opening]
    parameters: dict = field(default_factory=dict)

    def keep(self, points: np.ndarray) -> np.ndarray:
        """Positive where all openings keep the cloth, shape (N,)."""
        distinct = {id(o.keep): o.keep for o in self.openings}
        return np.min(np.stack([fn(points) for fn in distinct.values()]), axis=0)


# ----------------------------------------------------------------------------------- keep functions
def _smooth_max(a: np.ndarray, b: np.ndarray, radius: float) -> np.ndarray:
    """>= max(a, b); the corner of the level set max = 0 is rounded with about ``radius`` [m]."""
    return 0.5 * (a + b + np.sqrt((a - b) ** 2 + radius**2))


def _above(y0: float) -> Callable:
    """Keep y > y0 (a hem: the cloth is above it)."""
    return lambda p: p[:, 1] - y0


def _below(y0: float) -> Callable:
    """Keep y < y0 (a waistband)."""
    return lambda p: y0 - p[:, 1]


def _sleeve_end(shoulder: np.ndarray, elbow: np.ndarray, fraction: float) -> Callable:
    """Keep the side of the plane across the arm, at ``fraction`` of the way shoulder -> elbow."""
    axis = (elbow - shoulder) / np.linalg.norm(elbow - shoulder)
    point = shoulder + fraction * (elbow - shoulder)
    return lambda p: (point - p) @ axis


def _armhole(landmarks: BodyLandmarks, sign: float, x_inner: float, y_low: float, radius: float) -> Callable:
    """Keep the cloth unless it is both outside |x - cx| = x_inner (on side ``sign``) and above y_low.

    The removed region holds the arm and the side of the torso above y_low: a sleeveless armhole
    going over the shoulder at x_inner and under the arm at y_low, corners rounded by ``radius``.
    """
    cx = landmarks.center_x
    return lambda p: _smooth_max(x_inner - sign * (p[:, 0] - cx), y_low - p[:, 1], radius)


def _neck_bowl(front: tuple[float, float], back: tuple[float, float], side: tuple[float, float],
               axis_xz: tuple[float, float], kappa_z: float) -> tuple[Callable, dict]:
    """Neckline: keep the cloth below the bowl y = y0 + kappa_x u^2 + kappa_z w^2 - tilt w.

    u = x - x_neck, w = z - z_neck (the neck joint's axis). The front and back points, (w, y) at
    u = 0, fix y0 and tilt (> 0 lowers the front); the side point (r, y) at w = 0 fixes kappa_x.
    kappa_x, kappa_z > 0 make the bowl rise away from the neck, so it meets the envelope in one
    loop round the neck. The keep value is divided by the bowl's slope so it is close to a distance.
    """
    (wf, yf), (wb, yb), (rs, ys) = front, back, side
    a = np.array([[1.0, -wf], [1.0, -wb]])
    y0, tilt = np.linalg.solve(a, np.array([yf - kappa_z * wf**2, yb - kappa_z * wb**2]))
    kappa_x = (ys - y0) / rs**2
    if kappa_x <= 0.0:
        raise InputError(f"neckline points front {front}, back {back}, side {side} give a bowl that does not "
                         f"rise away from the neck (kappa_x = {kappa_x:.2f} 1/m)")
    nx, nz = axis_xz

    def keep(p):
        u, w = p[:, 0] - nx, p[:, 2] - nz
        cut = y0 + kappa_x * u * u + kappa_z * w * w - tilt * w
        slope = np.sqrt(1.0 + (2 * kappa_x * u) ** 2 + (2 * kappa_z * w - tilt) ** 2)
        return (cut - p[:, 1]) / slope

    return keep, {"y0": round(float(y0), 4), "kappa_x_per_m": round(float(kappa_x), 3),
                  "kappa_z_per_m": round(float(kappa_z), 3), "tilt": round(float(tilt), 3)}


# ----------------------------------------------------------------------------------- body probes
class _Probe:
    """Positions on the body surface used to place necklines."""

    def __init__(self, body, landmarks: BodyLandmarks):
        self.v = np.asarray(body.v_template, dtype=np.float64)
        self.edges = body_edges(body.faces)
        self.lm = landmarks

    def front_z(self, y: float, x: float, half_width: float) -> float:
        """Largest z [m] of the skin at height y within |x' - x| < half_width (the front surface)."""
        p = horizontal_section(self.v, self.edges, y)
        p = p[np.abs(p[:, 0] - x) < half_width]
        return float(p[:, 2].max())

    def back_z(self, y: float, x: float, half_width: float) -> float:
        """Smallest z [m] of the skin at height y within |x' - x| < half_width (the back surface)."""
        p = horizontal_section(self.v, self.edges, y)
        p = p[np.abs(p[:, 0] - x) < half_width]
        return float(p[:, 2].min())

    def top_y(self, x: float, z: float, below: float) -> float:
        """Highest skin point [m] on the vertical line (x, z) under height ``below`` (shoulder tops)."""
        p = horizontal_section(self.v, self.edges, x, axis=0)
        p = p[(np.abs(p[:, 2] - z) < 0.01 * self.lm.scale) & (p[:, 1] < below)]
        return float(p[:, 1].max())


def _neckline(probe: _Probe, lm: BodyLandmarks, *, front_y: float, back_y: float, side_r: float,
              ease: float) -> tuple[Callable, dict]:
    """A neckline through the front at ``front_y``, the back at ``back_y`` and over the shoulders
    at ``side_r`` from the neck axis, each point lying ``ease`` [m] off the skin."""
    neck = lm.joint("neck")
    s = lm.scale
    wf = probe.front_z(front_y, neck[0], 0.02 * s) - neck[2] + ease
    wb = probe.back_z(back_y, neck[0], 0.02 * s) - neck[2] - ease
    ys = max(probe.top_y(neck[0] + side_r, neck[2], neck[1] + 0.02 * s),
             probe.top_y(neck[0] - side_r, neck[2], neck[1] + 0.02 * s)) + ease
    # The bowl's curvature front to back; 3 /m on a 1.70 m body keeps the neckline round.
    kappa_z = 3.0 / lm.scale
    keep, params = _neck_bowl((wf, front_y), (wb, back_y), (side_r, ys), (float(neck[0]), float(neck[2])),
                              kappa_z)
    params.update(front_y=round(front_y, 4), back_y=round(back_y, 4), side_radius=round(side_r, 4))
    return keep, params


# ----------------------------------------------------------------------------------- ease profiles
def _profile(heights, values) -> Callable[[np.ndarray], np.ndarray]:
    """Piecewise-linear ease [m] over height y [m] (held constant outside the knots)."""
    order = np.argsort(heights)
    h = np.asarray(heights, dtype=np.float64)[order]
    e = np.asarray(values, dtype=np.float64)[order]
    return lambda y: np.interp(y, h, e)


def _with_arms(lm: BodyLandmarks, torso: Callable, arm_start: float, arm_end: float,
               sleeve_fraction: float) -> Callable:
    """Ease [m] at points (N, 3): the torso profile over height, blended into an arm profile.

    Along each arm the ease goes linearly from ``arm_start`` at the shoulder joint to ``arm_end``
    at ``sleeve_fraction`` of the way to the elbow; the blend between torso and arm happens from 3
    cm inside to 5 cm outside the shoulder joint, measured along the arm, and only within 10-16 cm
    of the arm's axis (a wide skirt below the arms keeps the torso profile).
    """
    sides = []
    for sh, el in (("left_shoulder", "left_elbow"), ("right_shoulder", "right_elbow")):
        a, b = lm.joint(sh), lm.joint(el)
        axis = (b - a) / np.linalg.norm(b - a)
        sides.append((a, axis, np.linalg.norm(b - a)))
    s = lm.scale

    def ease(p):
        e = torso(p[:, 1])
        for a, axis, length in sides:
            along = (p - a) @ axis
            radial = np.linalg.norm(p - a - along[:, None] * axis, axis=1)
            arm = arm_start + (arm_end - arm_start) * np.clip(along / (sleeve_fraction * length), 0.0, 1.0)
            near_arm = 1.0 - smoothstep((radial - 0.10 * s) / (0.06 * s))
            blend = smoothstep((along + 0.03 * s) / (0.08 * s)) * near_arm
            e = (1.0 - blend) * e + blend * arm
        return e

    return ease


# ----------------------------------------------------------------------------------- recipes
def _box(body, lm: BodyLandmarks, y_low: float, y_high: float, half_width: float, pad: float) -> np.ndarray:
    """Contouring region [m] (2, 3): heights [y_low, y_high], |x - cx| <= half_width, the body's
    depth over those heights plus ``pad`` in z."""
    v = np.asarray(body.v_template)
    sel = (v[:, 1] > y_low) & (v[:, 1] < y_high) & (np.abs(v[:, 0] - lm.center_x) < half_width)
    z = v[sel, 2]
    return np.array([[lm.center_x - half_width, y_low, z.min() - pad],
                     [lm.center_x + half_width, y_high, z.max() + pad]])


def _top_recipe(name: str, body, lm: BodyLandmarks, edge_length: float) -> TemplateRecipe:
    """tshirt, tank_top and the bodice of the dress share the neck, shoulders and torso."""
    s = lm.scale
    neck = lm.joint("neck")
    knee_y = float(lm.joints[[4, 5], 1].mean())
    armpit = float(lm.armpit_y.min())
    shoulders = [lm.joint("left_shoulder"), lm.joint("right_shoulder")]
    elbows = [lm.joint("left_elbow"), lm.joint("right_elbow")]
    shoulder_half = float(np.mean([abs(sh[0] - lm.center_x) for sh in shoulders]))
    probe = _Probe(body, lm)
    params: dict = {}
    if name == "tshirt":
        hem_y = lm.crotch_y + 0.08 * s
        torso = _profile([hem_y, lm.waist_y, armpit - 0.05 * s, armpit + 0.05 * s],
                         [0.035 * s, 0.030 * s, 0.025 * s, 0.012 * s])
        sleeve = 0.45
        # Sleeve ease 1.3 cm at the shoulder joint, 0.8 cm at the opening: a 33.3 cm opening on
        # the arm's 28.6 cm, between the S and the M of a published chart (docs/garment_sizes.md).
        # With 3 cm (46.9 cm) the ring hung on one side of the lowered arm and stood up to 6.8 cm
        # off it on the other in the walk (BENCHMARKS.md, 2026-11-29).
        ease = _with_arms(lm, torso, 0.013 * s, 0.008 * s, sleeve)
        neck_keep, neck_params = _neckline(probe, lm, front_y=neck[1] - 0.05 * s, back_y=neck[1] + 0.005 * s,
                                           side_r=lm.neck_extent[0] + 0.02 * s, ease=0.012 * s)
        openings = [Opening("neck", neck_keep), Opening("hem", _above(hem_y)),
                    Opening("left_sleeve", _sleeve_end(shoulders[0], elbows[0], sleeve)),
                    Opening("right_sleeve", _sleeve_end(shoulders[1], elbows[1], sleeve))]
        reach = max(abs((sh + sleeve * (el - sh))[0] - lm.center_x) for sh, el in zip(shoulders, elbows))
        half_width = reach + 0.08 * s
        y_low, y_high = hem_y - 0.05 * s, neck[1] + 0.12 * s
        params.update(hem_y=round(hem_y, 4), sleeve_fraction=sleeve)
    else:
        # Shoulder straps between the neckline and the armholes: 4 cm, and at least 1.5 edge
        # lengths so that a coarse variant still has cloth across the strap.
        strap = max(0.04 * s, 1.5 * edge_length)
        neck_side = max(shoulder_half - 0.09 * s, lm.neck_extent[0] + 0.015 * s)
        x_inner = max(shoulder_half - (0.045 if name == "tank_top" else 0.04) * s, neck_side + strap)
        y_low = armpit - (0.05 if name == "tank_top" else 0.035) * s
        if name == "tank_top":
            hem_y = lm.crotch_y + 0.10 * s
            torso = _profile([hem_y, lm.waist_y, armpit - 0.05 * s, armpit + 0.05 * s],
                             [0.025 * s, 0.020 * s, 0.018 * s, 0.010 * s])
        else:  # dress: A-line skirt from the hips to below the knees
            hem_y = knee_y - 0.08 * s
            hip_y = float(lm.joints[[1, 2], 1].mean())
            torso = _profile([hem_y, lm.crotch_y, hip_y, lm.waist_y, armpit - 0.05 * s, armpit + 0.05 * s],
                             [0.12 * s, 0.05 * s, 0.03 * s, 0.02 * s, 0.018 * s, 0.010 * s])
        ease = _with_arms(lm, torso, 0.015 * s, 0.015 * s, 0.5)
        neck_keep, neck_params = _neckline(probe, lm, front_y=neck[1] - 0.13 * s, back_y=neck[1] - 0.025 * s,
                                           side_r=x_inner - strap, ease=0.010 * s)
        openings = [Opening("neck", neck_keep), Opening("hem", _above(hem_y)),
                    Opening("left_armhole", _armhole(lm, 1.0, x_inner, y_low, 0.04 * s)),
                    Opening("right_armhole", _armhole(lm, -1.0, x_inner, y_low, 0.04 * s))]
        half_width = shoulder_half + 0.12 * s
        params.update(hem_y=round(hem_y, 4), armhole_x=round(x_inner, 4), armhole_y=round(y_low, 4),
                      strap_width=round(strap, 4))
        y_low, y_high = hem_y - 0.05 * s, neck[1] + 0.12 * s
    params["neckline"] = neck_params
    hull = HullSpec(top_y=armpit - 0.03 * s, fade=0.05 * s, drape_below_y=lm.waist_y if name == "dress" else None)
    pad = 0.06 * s if name != "dress" else 0.16 * s
    return TemplateRecipe(box=_box(body, lm, y_low, y_high, half_width, pad), ease=ease, hull=hull,
                          openings=openings, parameters=params)


def _lower_recipe(name: str, body, lm: BodyLandmarks) -> TemplateRecipe:
    """skirt, pants and shorts: a waistband and one hem (skirt) or two leg hems."""
    s = lm.scale
    knee_y = float(lm.joints[[4, 5], 1].mean())
    ankle_y = float(lm.joints[[7, 8], 1].mean())
    hip_y = float(lm.joints[[1, 2], 1].mean())
    params: dict = {}
    if name == "skirt":
        top_y = lm.waist_y - 0.03 * s
        hem_y = knee_y + 0.11 * s
        ease_fn = _profile([hem_y, lm.crotch_y, hip_y, top_y], [0.07 * s, 0.035 * s, 0.022 * s, 0.012 * s])
        hull = HullSpec(top_y=lm.waist_y + 0.10 * s, drape_below_y=lm.waist_y)
        openings = [Opening("waist", _below(top_y)), Opening("hem", _above(hem_y))]
        half_width = 0.45 * s
    else:
        top_y = lm.waist_y - 0.06 * s
        if name == "pants":
            hem_y = ankle_y + 0.05 * s
            ease_fn = _profile([hem_y, knee_y, lm.crotch_y, hip_y, top_y],
                               [0.035 * s, 0.030 * s, 0.020 * s, 0.018 * s, 0.012 * s])
        else:
            hem_y = lm.crotch_y - 0.13 * s
            ease_fn = _profile([hem_y, lm.crotch_y, hip_y, top_y], [0.03 * s, 0.02 * s, 0.018 * s, 0.012 * s])
        crotch_ease = float(ease_fn(np.array([lm.crotch_y]))[0])
        hull = HullSpec(top_y=lm.waist_y + 0.10 * s, per_leg_below_y=lm.crotch_y,
                        leg_gap_below_y=lm.crotch_y - crotch_ease, leg_gap=0.004 * s)
        hem = _above(hem_y)
        openings = [Opening("waist", _below(top_y)), Opening("left_hem", hem, "left"),
                    Opening("right_hem", hem, "right")]
        half_width = 0.40 * s
    params.update(waist_y=round(top_y, 4), hem_y=round(hem_y, 4))
    ease = lambda p: ease_fn(p[:, 1])  # noqa: E731 - the recipes' ease is a function of points
    box = _box(body, lm, hem_y - 0.05 * s, top_y + 0.08 * s, half_width, 0.12 * s)
    return TemplateRecipe(box=box, ease=ease, hull=hull, openings=openings, parameters=params)


def template_recipe(name: str, body, landmarks: BodyLandmarks | None = None, *,
                    edge_length: float = 0.0) -> TemplateRecipe:
    """The recipe (region, ease, hulls, openings, parameters) of template ``name`` on ``body``.

    edge_length [m]: the expected edge length; narrow parts (shoulder straps) are widened to
    stay at least 1.5 edge lengths wide.
    """
    if name not in TEMPLATE_NAMES:
        raise InputError(f"unknown garment template {name!r}; templates are {', '.join(TEMPLATE_NAMES)}")
    lm = landmarks if landmarks is not None else body_landmarks(body)
    if name in ("tshirt", "tank_top", "dress"):
        return _top_recipe(name, body, lm, edge_length)
    return _lower_recipe(name, body, lm)


# ----------------------------------------------------------------------------------- generation
def _name_loops(vertices: np.ndarray, loops: list[np.ndarray], openings: list[Opening], center_x: float) -> list[str]:
    """Name each boundary loop after the opening whose keep function vanishes on it."""
    names = []
    for loop in loops:
        p = vertices[loop]
        side = "left" if p[:, 0].mean() >= center_x else "right"
        best, best_err = "unknown", np.inf
        for o in openings:
            if o.side is not None and o.side != side:
                continue
            err = float(np.abs(o.keep(p)).mean())
            if err < best_err:
                best, best_err = o.name, err
        names.append(best)
    return names


def generate_template(name: str, body, *, target_triangles: int | None = None, seed: int = 0):
    """Generate template ``name`` on ``body`` in rest pose.

    Args:
        name: one of :data:`TEMPLATE_NAMES`.
        body: a :class:`simgen.body.BodyModel`; its rest template (betas 0, T-pose) is dressed.
        target_triangles: triangle count to aim for (default :data:`DEFAULT_TRIANGLES`); the
            result is within a few percent. At least 300.
        seed: 0 gives the canonical triangulation; any other value gives an equally good but
            different one of the same surface (the remesher visits the mesh in another order).

    Returns:
        vertices [m], shape (V, 3); faces, int64 shape (F, 3), counter-clockwise seen from outside;
        info: dict with "openings" (one entry per boundary loop: name, vertex count, perimeter [m],
        centroid [m]), "landmarks", "parameters" (the recipe's numbers, edge length [m], grid
        spacing [m]), "pushed_out" (vertices moved out to the clearance), "snapped_to_openings"
        (boundary vertices put back on their opening's curve) and "seconds".

    Raises:
        InputError: unknown name, target below 300, a body not in a T-pose, or a body on which
        the openings of this template touch each other at this size.
    """
    from simgen.garment import remesh as rm
    from simgen.garment.envelope import envelope_field, envelope_surface
    from simgen.garment.mesh import boundary_loops, triangle_areas

    t_start = time.perf_counter()
    if name not in TEMPLATE_NAMES:
        raise InputError(f"unknown garment template {name!r}; templates are {', '.join(TEMPLATE_NAMES)}")
    target = DEFAULT_TRIANGLES[name] if target_triangles is None else int(target_triangles)
    if target < 300:
        raise InputError(f"target_triangles must be at least 300, got {target_triangles}")
    lm = body_landmarks(body)
    s = lm.scale
    area_guess = _AREA_HINT[name] * s * s
    edge_guess = float(np.sqrt(4.0 * area_guess / (np.sqrt(3.0) * target)))
    recipe = template_recipe(name, body, lm, edge_length=edge_guess)

    # Grid spacing: about a third of the expected edge length, between 5 and 12 mm.
    spacing = float(np.clip(edge_guess / 3.5, 0.005 * s, 0.012 * s))
    grid = envelope_field(body, recipe.box, spacing, recipe.ease, hull=recipe.hull, landmarks=lm, blur=0.005 * s)
    env_v, env_f = envelope_surface(grid)
    split_v, split_f, curve = rm.split_along_level_set(env_v, env_f, recipe.keep(env_v))
    inside = recipe.keep(split_v[split_f].mean(axis=1)) > 0.0
    area = float(triangle_areas(split_v, split_f[inside]).sum())

    # Equilateral triangles of edge L have area sqrt(3)/4 L^2; the remesher's triangles are close.
    edge = float(np.sqrt(4.0 * area / (np.sqrt(3.0) * target)))
    for attempt in range(3):
        v, f = rm.remesh(split_v, split_f, edge, curve_edges=curve, seed=seed)
        v, f = rm.cut(v, f, recipe.keep)
        ratio = len(f) / target
        if abs(ratio - 1.0) <= 0.03 or attempt == 2:
            break
        edge *= float(np.sqrt(ratio))

    # Where an opening turns sharply at a coarse edge length, a few boundary vertices can sit
    # beside the curve: put them back on it. The cut also leaves a few thin triangles along the
    # openings; flips and tangential smoothing on the envelope fix them without moving the openings.
    reference = (split_v, split_f)
    try:
        v, f, _ = rm.repair_bowties(v, f)
        off_curve = 0
        for _ in range(2):  # the second round catches short boundary edges left by the even spacing
            v, f = rm.clean_boundary(v, f, edge)
            v, off = rm.snap_boundary(v, f, recipe.keep, reference, iterations=20, spacing_iterations=14)
            off_curve = max(off_curve, off)
            v, f = rm.relax(v, f, reference, edge_length=edge, iterations=5)
        loops = boundary_loops(f)
    except ValueError as exc:  # openings touching: the recipe does not fit this body at this size
        raise InputError(f"template {name!r} cannot be cut cleanly on body {getattr(body, 'name', '?')!r} at "
                         f"{target} triangles ({exc})") from None
    v, pushed = rm.push_outside(v, body.v_template, body.faces, CLEARANCE + CLEARANCE_MARGIN)
    names = _name_loops(v, loops, recipe.openings, lm.center_x)
    openings = []
    for loop, loop_name in sorted(zip(loops, names), key=lambda item: item[1]):
        p = v[loop]
        openings.append({
            "name": loop_name,
            "num_vertices": int(len(loop)),
            "perimeter_m": round(float(np.linalg.norm(p - np.roll(p, 1, axis=0), axis=1).sum()), 4),
            "centroid_m": [round(float(c), 4) for c in p.mean(axis=0)],
        })
    info = {
        "template": name,
        "openings": openings,
        "landmarks": lm.to_dict(),
        "parameters": {
            **recipe.parameters,
            "target_triangles": target,
            "edge_length_m": round(edge, 5),
            "grid_spacing_m": round(spacing, 5),
            "clearance_m": CLEARANCE + CLEARANCE_MARGIN,
            "generator_version": GENERATOR_VERSION,
            "seed": int(seed),
        },
        "pushed_out": pushed,
        "snapped_to_openings": off_curve,
        "seconds": round(time.perf_counter() - t_start, 2),
    }
    return v, f, info
