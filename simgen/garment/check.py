"""The garment quality contract: ``check_garment(garment, body) -> CheckReport``.

Generic items (every garment, imported ones included):

- ``body``: the garment was made on this body (metadata hash equals the body's), when recorded;
- ``manifold_edges``: no edge is shared by more than two triangles;
- ``manifold_vertices``: every vertex's triangles form one fan (no bow-tie vertices), so the
  boundary splits into well-defined loops;
- ``single_component``: one connected piece of cloth, no unreferenced vertices;
- ``consistent_orientation``: each interior edge is walked once in each direction;
- ``outward_orientation``: normals point away from the body: the mesh closed by a fan over each
  opening has positive signed volume, and at least 90 % of the vertex normals point away from
  the closest body point;
- ``openings``: the number of boundary loops (exactly :data:`EXPECTED_OPENINGS` for a template);
- ``min_angle``: every triangle angle >= :data:`MIN_ANGLE_DEG`;
- ``edge_spread``: edge lengths (percentiles 1, 50, 99 reported) within
  p99 / p1 <= :data:`MAX_EDGE_P99_P1` and max / min <= :data:`MAX_EDGE_RATIO`;
- ``not_inside``: no vertex inside the body (signed distance, winding number);
- ``clearance``: every vertex at least :data:`CLEARANCE` (2 mm) outside the body;
- ``ease``: distance to the body per region (the body joint that dominates the closest body point),
  mean and max, labelled tight (< 2 cm mean), regular or loose (> 5 cm); fails only when a region
  lies more than :data:`MAX_EASE` from the body (a garment floating away).

Template items, chosen by ``metadata["template"]`` (else by the name when it is a template's),
with landmarks from the body's rest joints and skin (:func:`simgen.garment.envelope.body_landmarks`):

- tshirt: ``coverage_sleeves`` (each sleeve ends between shoulder and elbow: the reach of the cloth
  within 10 cm of the arm's axis, along the shoulder -> elbow segment, is in (0.25, 1) of it),
  ``coverage_hem`` (hem below the natural waist), ``coverage_neck`` (the neck loop goes round the
  neck joint);
- tank_top: ``coverage_no_sleeves`` (no cloth round the arm past 15 % of the way to the elbow; each armhole's
  centre within 15 cm of its shoulder joint), ``coverage_hem``, ``coverage_neck``;
- dress: ``coverage_no_sleeves``, ``coverage_neck``, ``coverage_hem`` (hem above the floor and
  entirely below the knee joints), ``hem_clear_of_legs``;
- skirt: ``coverage_waist`` (waistband between the hip joints and 5 cm above the natural waist),
  ``coverage_hem`` (entirely above the knee joints), ``hem_clear_of_legs``;
- pants: ``coverage_waist``, ``coverage_hems`` (each leg hem's mean height within 10 cm of the
  ankle joints, above the floor);
- shorts: ``coverage_waist``, ``coverage_hems`` (each leg hem between the knees and the crotch);
- ``hem_clear_of_legs`` (skirt, dress): the hem loop seen from above goes once round both legs and
  the point between them (it does not pass between the legs), and every hem vertex is at least
  :data:`HEM_LEG_CLEARANCE` from the skin.

Lengths in the rules scale with the body's height / 1.70 m.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from simgen.body.surface import vertex_normals
from simgen.garment.templates import CLEARANCE, EXPECTED_OPENINGS, TEMPLATE_NAMES

__all__ = [
    "CheckItem",
    "CheckReport",
    "check_garment",
    "garment_template",
    "MIN_ANGLE_DEG",
    "MAX_EDGE_P99_P1",
    "MAX_EDGE_RATIO",
    "MAX_EASE",
    "HEM_LEG_CLEARANCE",
    "CLEARANCE",
]

MIN_ANGLE_DEG = 20.0
MAX_EDGE_P99_P1 = 2.5  # generated templates: ~1.7
MAX_EDGE_RATIO = 5.0  # generated templates: ~2.4-3.3 (short edges where an opening curves)
MAX_EASE = 0.30  # [m] a region whose cloth is further than this from the body is floating away
HEM_LEG_CLEARANCE = 0.02  # [m] skirt and dress hems stand this far from the legs (1.70 m body)
_OUTWARD_FRACTION = 0.9
_SLEEVE_MIN = 0.25  # a sleeve reaches at least a quarter of the way from the shoulder to the elbow
_NO_SLEEVE_MAX = 0.15  # sleeveless: no cloth round the arm past 15 % of the way to the elbow
_TIGHT, _LOOSE = 0.02, 0.05  # [m] mean ease labels


@dataclass
class CheckItem:
    """One rule of the contract: its name, whether it passed, one line of text and its numbers."""

    name: str
    passed: bool
    message: str
    values: dict = field(default_factory=dict)

    def to_dict(self) -> dict:
        return {"name": self.name, "passed": bool(self.passed), "message": self.message,
                "values": _jsonable(self.values)}


@dataclass
class CheckReport:
    """Result of :func:`check_garment`: one :class:`CheckItem` per rule."""

    garment: str
    template: str | None
    body: str
    items: list[CheckItem] = field(default_factory=list)

    @property
    def passed(self) -> bool:
        return all(item.passed for item in self.items)

    @property
    def failures(self) -> list[CheckItem]:
        return [item for item in self.items if not item.passed]

    def item(self, name: str) -> CheckItem:
        """The item called ``name`` (KeyError if the report has none)."""
        for it in self.items:
            if it.name == name:
                return it
        raise KeyError(f"check report of {self.garment!r} has no item {name!r}")

    def names(self) -> list[str]:
        return [item.name for item in self.items]

    def to_dict(self) -> dict:
        return {"garment": self.garment, "template": self.template, "body": self.body, "passed": self.passed,
                "items": [item.to_dict() for item in self.items]}

    def format(self) -> str:
        """Human-readable report: a header line, then one line per item."""
        kind = self.template if self.template else "imported garment (generic checks only)"
        verdict = "PASSED" if self.passed else f"FAILED ({len(self.failures)} of {len(self.items)} items)"
        lines = [f"garment {self.garment} [{kind}] on body {self.body}: {verdict}"]
        width = max(len(item.name) for item in self.items) if self.items else 0
        for item in self.items:
            lines.append(f"  {'ok  ' if item.passed else 'FAIL'} {item.name:<{width}}  {item.message}")
        return "\n".join(lines)


def _jsonable(value):
    if isinstance(value, dict):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    if isinstance(value, (np.floating, float)):
        return round(float(value), 6)
    if isinstance(value, (np.integer,)):
        return int(value)
    if isinstance(value, np.bool_):
        return bool(value)
    if isinstance(value, np.ndarray):
        return _jsonable(value.tolist())
    return value


def garment_template(garment) -> str | None:
    """The template a garment was made from: metadata["template"], else its name if it is a template's."""
    template = garment.metadata.get("template") if isinstance(garment.metadata, dict) else None
    if template in TEMPLATE_NAMES:
        return template
    return garment.name if garment.name in TEMPLATE_NAMES else None


# ----------------------------------------------------------------------------------- geometry helpers
def _winding_xz(loop_xz: np.ndarray, point: np.ndarray) -> int:
    """Winding number of a closed polygon (N, 2) in the xz plane around a point (2,)."""
    d = loop_xz - point
    ang = np.arctan2(d[:, 1], d[:, 0])
    turn = np.diff(np.r_[ang, ang[0]])
    turn = (turn + np.pi) % (2.0 * np.pi) - np.pi
    return int(round(turn.sum() / (2.0 * np.pi)))


def _closed_signed_volume(vertices: np.ndarray, faces: np.ndarray, loops: list[np.ndarray]) -> float:
    """Signed volume [m^3] of the mesh closed by a fan from each loop's centroid."""
    v = [vertices]
    f = [faces]
    n = len(vertices)
    for loop in loops:
        c = vertices[loop].mean(axis=0)
        v.append(c[None])
        # Boundary half-edges run a -> b in the loop's order; the cap walks them b -> a.
        a, b = loop, np.roll(loop, -1)
        f.append(np.stack([np.full(len(loop), n), b, a], axis=1))
        n += 1
    vv, ff = np.vstack(v), np.vstack(f)
    p0, p1, p2 = vv[ff[:, 0]], vv[ff[:, 1]], vv[ff[:, 2]]
    return float(np.einsum("ij,ij->i", p0, np.cross(p1, p2)).sum() / 6.0)


# ----------------------------------------------------------------------------------- the check
def check_garment(garment, body, *, template: str | None = None) -> CheckReport:
    """Check a garment against the quality contract (module docstring) on ``body`` in rest pose.

    garment: a :class:`simgen.garment.garment.Garment`; body: a BodyModel (its ``v_template``,
    ``faces``, ``weights`` and rest joints are used). ``template`` overrides the template read
    from the garment's metadata or name; unknown garments get the generic items only.
    Never raises on a bad mesh: every problem becomes a failed item.
    """
    from simgen.body import SMPL_JOINT_NAMES
    from simgen.body.surface import project_to_surface
    from simgen.garment import mesh as gm
    from simgen.garment.envelope import body_landmarks

    template = template if template is not None else garment_template(garment)
    if template is not None and template not in TEMPLATE_NAMES:
        template = None
    report = CheckReport(garment=garment.name, template=template, body=str(getattr(body, "model_id", "?")))
    add = report.items.append
    v, f = garment.vertices, garment.faces
    meta = garment.metadata if isinstance(garment.metadata, dict) else {}

    # --- body identity
    recorded = (meta.get("body") or {}).get("hash") if isinstance(meta.get("body"), dict) else None
    if recorded is None:
        add(CheckItem("body", True, "no body hash recorded; checked against the given body"))
    else:
        same = recorded == body.hash
        add(CheckItem("body", same, "made on this body" if same else
                      f"made on body {recorded[:12]}, checked on {body.hash[:12]}", {"recorded": recorded[:12]}))

    # --- topology
    nm_edges = gm.non_manifold_edges(f)
    add(CheckItem("manifold_edges", len(nm_edges) == 0,
                  "every edge has one or two triangles" if len(nm_edges) == 0
                  else f"{len(nm_edges)} edges have more than two triangles", {"non_manifold_edges": len(nm_edges)}))
    nm_verts = gm.non_manifold_vertices(f)
    loops: list[np.ndarray] | None
    try:
        loops = gm.boundary_loops(f)
        loop_problem = None
    except ValueError as exc:
        loops, loop_problem = None, str(exc)
    ok = len(nm_verts) == 0 and loop_problem is None
    add(CheckItem("manifold_vertices", ok, "every vertex has a single fan of triangles" if ok else
                  f"{len(nm_verts)} bow-tie vertices" + (f"; {loop_problem}" if loop_problem else ""),
                  {"non_manifold_vertices": len(nm_verts)}))
    n_comp, _ = gm.connected_components(f, len(v))
    unreferenced = len(v) - len(np.unique(f))
    ok = n_comp == 1 and unreferenced == 0
    add(CheckItem("single_component", ok, "one piece" if ok else
                  f"{n_comp} connected components, {unreferenced} unreferenced vertices",
                  {"components": n_comp, "unreferenced_vertices": unreferenced}))
    consistent = gm.is_consistently_oriented(f)
    add(CheckItem("consistent_orientation", consistent, "neighbouring triangles agree" if consistent
                  else "some edge is walked twice in the same direction (flipped triangles)"))

    proj = project_to_surface(v, body.v_template, body.faces)
    sd = proj.signed_distance
    normals = vertex_normals(v, f)
    away = v - proj.closest
    away_len = np.linalg.norm(away, axis=1)
    valid = away_len > 1e-6
    outward = float(np.mean(np.einsum("ij,ij->i", normals[valid], away[valid]) * np.sign(sd[valid]) > 0.0)) \
        if valid.any() else 0.0
    volume = _closed_signed_volume(v, f, loops) if loops is not None else float("nan")
    ok = consistent and bool(volume > 0.0) and outward >= _OUTWARD_FRACTION
    add(CheckItem("outward_orientation", ok,
                  f"closed volume {volume * 1e3:.1f} l, {outward:.0%} of vertex normals point away from the body "
                  f"(need > 0 and >= {_OUTWARD_FRACTION:.0%})",
                  {"closed_volume_m3": volume, "outward_fraction": outward}))

    # --- openings
    n_loops = len(loops) if loops is not None else -1
    if template is None:
        add(CheckItem("openings", loops is not None, f"{n_loops} boundary loops", {"openings": n_loops}))
    else:
        want = EXPECTED_OPENINGS[template]
        add(CheckItem("openings", n_loops == want, f"{n_loops} boundary loops, {template} needs {want}",
                      {"openings": n_loops, "expected": want}))

    # --- triangle and edge quality
    angles = gm.triangle_angles(v, f)
    min_angle = float(np.nanmin(angles)) if np.isfinite(angles).any() else 0.0
    if np.isnan(angles).any():
        min_angle = 0.0
    bad = int(np.sum(np.nan_to_num(angles.min(axis=1), nan=0.0) < MIN_ANGLE_DEG))
    add(CheckItem("min_angle", min_angle >= MIN_ANGLE_DEG,
                  f"smallest angle {min_angle:.1f} deg (need >= {MIN_ANGLE_DEG:.0f}), {bad} triangles below",
                  {"min_angle_deg": min_angle, "triangles_below": bad,
                   "angle_p1_deg": float(np.nanpercentile(angles.min(axis=1), 1))}))
    lengths = gm.edge_lengths(v, gm.unique_edges(f))
    p1, p50, p99 = (float(x) for x in np.percentile(lengths, [1, 50, 99]))
    lo, hi = float(lengths.min()), float(lengths.max())
    spread, ratio = p99 / max(p1, 1e-300), hi / max(lo, 1e-300)
    ok = spread <= MAX_EDGE_P99_P1 and ratio <= MAX_EDGE_RATIO
    add(CheckItem("edge_spread", ok,
                  f"edges p1/p50/p99 {p1 * 1e3:.1f}/{p50 * 1e3:.1f}/{p99 * 1e3:.1f} mm, p99/p1 {spread:.2f} "
                  f"(<= {MAX_EDGE_P99_P1}), max/min {ratio:.2f} (<= {MAX_EDGE_RATIO})",
                  {"p1_m": p1, "p50_m": p50, "p99_m": p99, "min_m": lo, "max_m": hi, "p99_over_p1": spread,
                   "max_over_min": ratio}))

    # --- clearance
    inside = int(np.sum(sd < 0.0))
    add(CheckItem("not_inside", inside == 0, "no vertex inside the body" if inside == 0
                  else f"{inside} vertices inside the body", {"vertices_inside": inside}))
    close = int(np.sum(sd < CLEARANCE))
    add(CheckItem("clearance", close == 0,
                  f"closest vertex {sd.min() * 1e3:.1f} mm outside the body (need >= {CLEARANCE * 1e3:.0f} mm), "
                  f"{close} vertices closer", {"min_signed_distance_m": float(sd.min()), "vertices_closer": close}))

    # --- ease per region
    tri = body.faces[proj.face]
    w = np.einsum("pk,pkj->pj", proj.bary, np.asarray(body.weights)[tri])
    region = w.argmax(axis=1)
    regions = {}
    for j in np.unique(region):
        d = away_len[region == j]
        mean = float(d.mean())
        label = "tight" if mean < _TIGHT else ("loose" if mean > _LOOSE else "regular")
        regions[SMPL_JOINT_NAMES[j]] = {"vertices": int(d.size), "mean_m": mean, "max_m": float(d.max()), "fit": label}
    worst = max(r["max_m"] for r in regions.values())
    tight = sorted((k for k, r in regions.items() if r["fit"] == "tight"), key=lambda k: regions[k]["mean_m"])
    loose = sorted((k for k, r in regions.items() if r["fit"] == "loose"), key=lambda k: -regions[k]["mean_m"])
    by_mean = sorted(regions, key=lambda k: regions[k]["mean_m"])
    summary = ", ".join(f"{k} {regions[k]['mean_m'] * 100:.1f}" for k in by_mean)
    add(CheckItem("ease", worst <= MAX_EASE,
                  f"mean distance to the body per region [cm]: {summary}; tight: {', '.join(tight) or 'none'}; "
                  f"loose: {', '.join(loose) or 'none'}; max {worst * 100:.1f} cm (<= {MAX_EASE * 100:.0f})",
                  {"regions": regions, "max_m": worst}))

    if template is not None:
        lm = body_landmarks(body)
        _template_items(report, template, v, loops, lm, away_len, body)
    return report


# ----------------------------------------------------------------------------------- template rules
def _classify_loops(template: str, v: np.ndarray, loops: list[np.ndarray], cx: float) -> dict[str, np.ndarray]:
    """Name the loops of a template with the expected count, from their centroids."""
    cent = np.array([v[loop].mean(axis=0) for loop in loops])
    idx = list(range(len(loops)))
    named: dict[str, np.ndarray] = {}
    if template in ("tshirt", "tank_top", "dress"):
        side = "sleeve" if template == "tshirt" else "armhole"
        by_x = sorted(idx, key=lambda i: cent[i, 0])
        named[f"right_{side}"], named[f"left_{side}"] = loops[by_x[0]], loops[by_x[-1]]
        rest = sorted(by_x[1:-1], key=lambda i: cent[i, 1])
        named["hem"], named["neck"] = loops[rest[0]], loops[rest[1]]
    elif template == "skirt":
        by_y = sorted(idx, key=lambda i: cent[i, 1])
        named["hem"], named["waist"] = loops[by_y[0]], loops[by_y[1]]
    else:
        by_y = sorted(idx, key=lambda i: cent[i, 1])
        named["waist"] = loops[by_y[-1]]
        hems = sorted(by_y[:2], key=lambda i: cent[i, 0])
        named["right_hem"], named["left_hem"] = loops[hems[0]], loops[hems[1]]
    return named


def _template_items(report: CheckReport, template: str, v: np.ndarray, loops, lm, dist: np.ndarray, body) -> None:
    add = report.items.append
    s = lm.scale
    if loops is None or len(loops) != EXPECTED_OPENINGS[template]:
        add(CheckItem("coverage", False, f"cannot place the openings of a {template}: "
                      f"{'ambiguous boundary' if loops is None else f'{len(loops)} loops'}"))
        return
    named = _classify_loops(template, v, loops, lm.center_x)
    knee_y = float(lm.joints[[4, 5], 1].mean())
    ankle_y = float(lm.joints[[7, 8], 1].mean())
    hip_y = float(lm.joints[[1, 2], 1].mean())

    def reach_along_arm(side: str) -> tuple[float, float]:
        """Cloth reach along the shoulder -> elbow segment (0 at the shoulder, 1 at the elbow) on one side."""
        sh, el = lm.joint(f"{side}_shoulder"), lm.joint(f"{side}_elbow")
        seg = el - sh
        t = (v - sh) @ seg / float(seg @ seg)
        radial = np.linalg.norm(v - sh - t[:, None] * seg, axis=1)
        # Cloth round the arm: within 10 cm of its axis (a wide skirt below the arm does not count).
        near = ((v[:, 0] - lm.center_x) * (1.0 if side == "left" else -1.0) > 0) & (radial < 0.10 * s)
        return (float(t[near].max()) if near.any() else 0.0), float(np.linalg.norm(seg))

    if template in ("tshirt", "tank_top", "dress"):
        neck = lm.joint("neck")
        wn = _winding_xz(v[named["neck"]][:, [0, 2]], neck[[0, 2]])
        lowest = float(v[named["neck"], 1].min())
        ok = abs(wn) == 1 and lowest > float(lm.armpit_y.min()) - 0.1 * s
        add(CheckItem("coverage_neck", ok, f"neck loop winds {abs(wn)} time(s) round the neck joint, lowest point "
                      f"{lowest:.3f} m (armpits at {lm.armpit_y.min():.3f} m)", {"winding": wn, "lowest_y_m": lowest}))
    if template == "tshirt":
        reach = {side: reach_along_arm(side)[0] for side in ("left", "right")}
        ok = all(_SLEEVE_MIN < r < 1.0 for r in reach.values())
        add(CheckItem("coverage_sleeves", ok,
                      "sleeves end at " + ", ".join(f"{k} {r:.2f}" for k, r in reach.items())
                      + f" of the way from shoulder to elbow (need between {_SLEEVE_MIN} and 1)", {"reach": reach}))
    if template in ("tank_top", "dress"):
        reach = {side: reach_along_arm(side)[0] for side in ("left", "right")}
        dists = {side: float(np.linalg.norm(v[named[f"{side}_armhole"]].mean(axis=0) - lm.joint(f"{side}_shoulder")))
                 for side in ("left", "right")}
        ok = all(r <= _NO_SLEEVE_MAX for r in reach.values()) and all(d < 0.15 * s for d in dists.values())
        add(CheckItem("coverage_no_sleeves", ok,
                      "cloth reaches " + ", ".join(f"{k} {r:.2f}" for k, r in reach.items())
                      + f" of the way to the elbows (need <= {_NO_SLEEVE_MAX}); armhole centres "
                      + ", ".join(f"{k} {d * 100:.1f} cm" for k, d in dists.items())
                      + f" from the shoulder joints (need < {15 * s:.0f} cm)",
                      {"reach": reach, "armhole_to_shoulder_m": dists}))
    if template in ("tshirt", "tank_top"):
        top = float(v[named["hem"], 1].max())
        add(CheckItem("coverage_hem", top < lm.waist_y, f"hem at most {top:.3f} m, natural waist at {lm.waist_y:.3f} m "
                      f"(hem must be below)", {"hem_max_y_m": top, "waist_y_m": lm.waist_y}))
    if template == "dress":
        top, bottom = float(v[named["hem"], 1].max()), float(v[named["hem"], 1].min())
        ok = top < knee_y and bottom > lm.floor_y
        add(CheckItem("coverage_hem", ok, f"hem between {bottom:.3f} and {top:.3f} m, knees at {knee_y:.3f} m "
                      f"(hem must be below the knees, above the floor)", {"hem_max_y_m": top, "knee_y_m": knee_y}))
    if template in ("skirt", "pants", "shorts"):
        mean = float(v[named["waist"], 1].mean())
        hi = lm.waist_y + 0.05 * s
        ok = hip_y < mean < hi
        add(CheckItem("coverage_waist", ok, f"waistband at {mean:.3f} m (need between the hip joints {hip_y:.3f} m "
                      f"and 5 cm above the natural waist {hi:.3f} m)", {"waist_mean_y_m": mean}))
    if template == "skirt":
        bottom = float(v[named["hem"], 1].min())
        add(CheckItem("coverage_hem", bottom > knee_y, f"hem down to {bottom:.3f} m, knees at {knee_y:.3f} m "
                      f"(hem must be above the knees)", {"hem_min_y_m": bottom, "knee_y_m": knee_y}))
    if template == "pants":
        means = {k: float(v[named[k], 1].mean()) for k in ("left_hem", "right_hem")}
        ok = all(abs(m - ankle_y) < 0.10 * s and v[named[k], 1].min() > lm.floor_y for k, m in means.items())
        add(CheckItem("coverage_hems", ok, "leg hems at " + ", ".join(f"{k} {m:.3f} m" for k, m in means.items())
                      + f", ankles at {ankle_y:.3f} m (need within {10 * s:.0f} cm)", {"hem_mean_y_m": means}))
    if template == "shorts":
        lows = {k: float(v[named[k], 1].min()) for k in ("left_hem", "right_hem")}
        highs = {k: float(v[named[k], 1].max()) for k in ("left_hem", "right_hem")}
        ok = all(lows[k] > knee_y and highs[k] < lm.crotch_y for k in lows)
        spans = ", ".join(f"{k} {lows[k]:.3f}-{highs[k]:.3f} m" for k in lows)
        add(CheckItem("coverage_hems", ok, f"leg hems between {spans}"
                      + f" (need above the knees {knee_y:.3f} m and below the crotch {lm.crotch_y:.3f} m)",
                      {"hem_min_y_m": lows, "hem_max_y_m": highs}))
    if template in ("skirt", "dress"):
        _hem_clear_of_legs(report, v, named["hem"], lm, dist, body)


def _hem_clear_of_legs(report: CheckReport, v: np.ndarray, hem: np.ndarray, lm, dist: np.ndarray, body) -> None:
    from simgen.garment.envelope import body_edges, horizontal_section

    y = float(v[hem, 1].mean())
    section = horizontal_section(np.asarray(body.v_template), body_edges(body.faces), y)
    left = section[section[:, 0] >= lm.center_x]
    right = section[section[:, 0] < lm.center_x]
    loop_xz = v[hem][:, [0, 2]]
    if len(left) == 0 or len(right) == 0:
        report.items.append(CheckItem("hem_clear_of_legs", False,
                                      f"no legs in the body section at the hem's height {y:.3f} m"))
        return
    centers = {"left leg": left[:, [0, 2]].mean(axis=0), "right leg": right[:, [0, 2]].mean(axis=0)}
    centers["between the legs"] = 0.5 * (centers["left leg"] + centers["right leg"])
    windings = {k: _winding_xz(loop_xz, c) for k, c in centers.items()}
    gap = float(dist[hem].min())
    need = HEM_LEG_CLEARANCE * lm.scale
    ok = all(abs(w) == 1 for w in windings.values()) and gap >= need
    report.items.append(CheckItem(
        "hem_clear_of_legs", ok,
        "hem goes round " + ", ".join(f"{k} {abs(w)}x" for k, w in windings.items())
        + f" (need 1 each); closest hem vertex {gap * 100:.1f} cm from the skin (need >= {need * 100:.1f} cm)",
        {"windings": windings, "min_hem_distance_m": gap}))
