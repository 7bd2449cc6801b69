"""Garment envelopes: smooth closed surfaces around the rest body from which templates are cut.

An envelope is the zero level set of a scalar field sampled on a regular grid over a box,

    F(p) = d_C(p) - ease(p)                                            [m]

where ``d_C`` is the signed distance to a "cover" C of the body and ``ease(p)`` [m] the gap the
garment keeps from it (tight at the shoulders and the waist, loose at hems). The cover is the body
itself, or the body united with horizontal convex hulls of its cross-sections ("hull slices"):
a horizontal hull bridges the concavities a garment spans (spine groove, under the bust, the navel)
and, for skirts and dresses, the gap between the legs, so that the cloth hangs clear of the legs
instead of wrapping each one. Pants hull each leg on its own below the crotch.

Pipeline: the body's signed distance (:func:`simgen.body.surface.project_to_surface`, exact, on a
grid of spacing 2h) is upsampled with cubic splines to the marching-cubes grid (spacing h; the
distance is smooth away from the body's medial axis, so this loses well under a millimetre), the
hull distances are computed per grid row of constant height, F is blurred with a Gaussian of 5 mm
(the union ``min`` leaves creases) and contoured with marching cubes. The grid's border is
forced outside, so the envelope is closed: where it crosses the box it is capped, and the caps are
always cut away later with the head, the hands or the feet.

Everything is expressed through :class:`BodyLandmarks`, measured on the body in rest pose (joint
positions and horizontal sections of the skin), so the same recipe fits any SMPL-format body.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from simgen.errors import InputError

__all__ = [
    "BodyLandmarks",
    "body_landmarks",
    "body_edges",
    "horizontal_section",
    "HullSpec",
    "EnvelopeGrid",
    "envelope_field",
    "envelope_surface",
    "smoothstep",
]

_ARM_JOINTS = (16, 17, 18, 19, 20, 21, 22, 23)  # shoulders (upper arms), elbows, wrists, hands


def smoothstep(t):
    """C1 ramp: 0 for t <= 0, 1 for t >= 1, 3t^2 - 2t^3 between (array in, array out)."""
    t = np.clip(t, 0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


# ------------------------------------------------------------------------------------ body sections
def body_edges(faces: np.ndarray) -> np.ndarray:
    """Unique undirected edges (E, 2) of a triangle mesh with faces (F, 3)."""
    f = np.asarray(faces, dtype=np.int64)
    e = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    return np.unique(np.sort(e, axis=1), axis=0)


def horizontal_section(vertices: np.ndarray, edges: np.ndarray, value: float, axis: int = 1,
                       weights: np.ndarray | None = None):
    """Points where mesh edges cross the plane ``coordinate[axis] = value``.

    vertices [m] (V, 3); edges (E, 2). Returns points [m], shape (K, 3), and, when ``weights``
    (V, C) is given, the per-point linear interpolation of those weights, shape (K, C).
    """
    a = vertices[edges[:, 0], axis]
    b = vertices[edges[:, 1], axis]
    cross = (a - value) * (b - value) < 0.0
    ea, eb = edges[cross, 0], edges[cross, 1]
    t = ((value - a[cross]) / (b[cross] - a[cross]))[:, None]
    points = vertices[ea] + t * (vertices[eb] - vertices[ea])
    if weights is None:
        return points
    return points, weights[ea] + t * (weights[eb] - weights[ea])


def _hull_perimeter(points_xz: np.ndarray) -> float:
    from scipy.spatial import ConvexHull

    if len(points_xz) < 3:
        return 0.0
    return float(ConvexHull(points_xz).area)  # in 2D qhull's "area" is the perimeter


@dataclass(frozen=True)
class BodyLandmarks:
    """Anthropometric landmarks of a body in rest pose (T-pose, Y-up, metres, front +Z).

    joints [m], shape (24, 3): rest joints (SMPL order).
    center_x [m]: the pelvis joint's x (the body's mid-sagittal plane).
    floor_y, top_y [m]: lowest and highest skin point; height = top_y - floor_y.
    waist_y [m]: height of the natural waist, the horizontal section of smallest convex-hull
      perimeter (a tape measure) of the torso between the pelvis and spine3 joints (arms excluded).
    crotch_y [m]: lowest skin point of the mid-sagittal section between the knees and the pelvis.
    armpit_y [m], shape (2,): lowest skin point dominated by the left / right upper arm (shoulder
      joint) in the body's skinning weights: the top of the armpit.
    neck_extent [m], shape (3,): the neck at the neck joint's height, relative to the joint's
      (x, z): half width, front (max z - z_neck) and back (min z - z_neck, negative).
    scale: height / 1.70 m, used to scale the length parameters of the garment recipes.
    """

    joints: np.ndarray
    center_x: float
    floor_y: float
    top_y: float
    waist_y: float
    crotch_y: float
    armpit_y: np.ndarray
    neck_extent: np.ndarray
    scale: float

    def joint(self, name: str) -> np.ndarray:
        """Rest position [m], shape (3,), of the SMPL joint called ``name``."""
        from simgen.body import SMPL_JOINT_NAMES

        return self.joints[SMPL_JOINT_NAMES.index(name)]

    @property
    def height(self) -> float:
        return self.top_y - self.floor_y

    def to_dict(self) -> dict:
        """JSON-ready summary (metres)."""
        return {
            "center_x": round(self.center_x, 4), "floor_y": round(self.floor_y, 4), "top_y": round(self.top_y, 4),
            "waist_y": round(self.waist_y, 4), "crotch_y": round(self.crotch_y, 4),
            "armpit_y": [round(float(a), 4) for a in self.armpit_y],
            "neck_extent": [round(float(a), 4) for a in self.neck_extent], "scale": round(self.scale, 4),
        }


def body_landmarks(body) -> BodyLandmarks:
    """Measure :class:`BodyLandmarks` on ``body.v_template`` (betas 0) and ``body.faces``.

    Raises InputError when the body is not in a T-pose-like rest pose (arms roughly horizontal,
    legs below the pelvis), which every recipe here assumes.
    """
    v = np.asarray(body.v_template, dtype=np.float64)
    joints = np.asarray(body.rest_joints()[0], dtype=np.float64)
    weights = np.asarray(body.weights, dtype=np.float64)
    edges = body_edges(body.faces)
    pelvis, spine3, neck = joints[0], joints[9], joints[12]
    knees = joints[[4, 5]]
    shoulders, elbows = joints[[16, 17]], joints[[18, 19]]
    arm_dir = elbows - shoulders
    if (np.any(np.abs(arm_dir[:, 1]) > 0.5 * np.linalg.norm(arm_dir, axis=1)) or knees[:, 1].max() >= pelvis[1]
            or neck[1] <= pelvis[1]):
        raise InputError(f"body {getattr(body, 'name', '?')!r}: garment templates need a T-pose rest body "
                         f"(arms within 30 deg of horizontal, knees below the pelvis)")
    floor_y, top_y = float(v[:, 1].min()), float(v[:, 1].max())
    scale = (top_y - floor_y) / 1.70

    # Natural waist: narrowest torso section; arm points are left out of the hull (arms may droop).
    arm_weight = weights[:, list(_ARM_JOINTS)].sum(axis=1, keepdims=True)
    best = (np.inf, pelvis[1])
    for y in np.linspace(pelvis[1], spine3[1], 48):
        pts, aw = horizontal_section(v, edges, y, weights=arm_weight)
        pts = pts[aw[:, 0] < 0.5]
        perimeter = _hull_perimeter(pts[:, [0, 2]])
        if 0.0 < perimeter < best[0]:
            best = (perimeter, y)
    waist_y = float(best[1])

    sag = horizontal_section(v, edges, float(pelvis[0]), axis=0)
    between = sag[(sag[:, 1] > knees[:, 1].max()) & (sag[:, 1] < pelvis[1])]
    crotch_y = float(between[:, 1].min()) if len(between) else float(pelvis[1] - 0.1 * scale)

    dominant = weights.argmax(axis=1)
    armpit = []
    for j in (16, 17):
        sel = dominant == j
        armpit.append(float(v[sel, 1].min()) if np.any(sel) else float(joints[j, 1] - 0.07 * scale))

    ring = horizontal_section(v, edges, float(neck[1]))
    ring = ring[np.hypot(ring[:, 0] - neck[0], ring[:, 2] - neck[2]) < 0.15 * scale]
    if len(ring) < 3:
        raise InputError(f"body {getattr(body, 'name', '?')!r}: no neck section at the neck joint's height")
    neck_extent = np.array([np.abs(ring[:, 0] - neck[0]).max(), (ring[:, 2] - neck[2]).max(),
                            (ring[:, 2] - neck[2]).min()])
    return BodyLandmarks(joints=joints, center_x=float(pelvis[0]), floor_y=floor_y, top_y=top_y, waist_y=waist_y,
                         crotch_y=crotch_y, armpit_y=np.asarray(armpit), neck_extent=neck_extent, scale=float(scale))


# ------------------------------------------------------------------------------------ the field
@dataclass(frozen=True)
class HullSpec:
    """Which horizontal hulls join the cover C (see the module docstring).

    top_y [m]: hulls are used below this height and faded out over ``fade`` [m] towards it (above
      it the cover is the body alone: the arms join the torso there).
    per_leg_below_y [m] or None: below this height the left (x > center_x) and right parts of a
      section are hulled separately (pants, shorts); above it, and always when None, the whole
      section is one hull (tops, skirts, dresses).
    leg_gap_below_y [m] or None: below this height (the crotch seam) a slab of half-width
      ``leg_gap`` [m] round the mid-sagittal plane is kept outside the envelope, so the two legs
      stay apart even where the ease would make them meet (thighs close together).
    drape_below_y [m] or None: below this height each section's hull also holds the hull just
      above it, so the cover only widens downwards: cloth hangs straight from the widest part
      (bust, belly, seat) instead of following the body back in under it (skirts, dresses).
    """

    top_y: float
    fade: float = 0.05
    drape_below_y: float | None = None
    per_leg_below_y: float | None = None
    leg_gap_below_y: float | None = None
    leg_gap: float = 0.004


@dataclass
class EnvelopeGrid:
    """A scalar field on a regular grid.

    origin [m], shape (3,): position of sample (0, 0, 0); spacing [m]; values, shape (nx, ny, nz):
    F at origin + spacing * (i, j, k) (negative inside the envelope).
    """

    origin: np.ndarray
    spacing: float
    values: np.ndarray

    def points(self) -> np.ndarray:
        """Sample positions [m], shape (nx * ny * nz, 3), in C order of ``values``."""
        axes = [self.origin[i] + self.spacing * np.arange(self.values.shape[i]) for i in range(3)]
        return np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)


def _convex_polygon_distance(points: np.ndarray, polygon: np.ndarray) -> np.ndarray:
    """Signed distance [m] of 2D points (N, 2) to a convex polygon (K, 2), counter-clockwise; negative inside.

    The largest signed distance to the edges' lines: exact inside and wherever the nearest point
    is on an edge; near a corner it overestimates by d (1 / cos(a / 2) - 1) for a corner turning
    by a. Hulls of body sections have many short edges turning by a few degrees each (a = 10 deg
    costs 0.4 %), so the field keeps the hull's shape at a tenth of the cost of exact segment
    distances.
    """
    a = polygon
    ab = np.roll(polygon, -1, axis=0) - a
    length = np.maximum(np.linalg.norm(ab, axis=1), 1e-12)
    # Outward normal of a counter-clockwise edge (ab_x, ab_z) is (ab_z, -ab_x).
    normal = np.stack([ab[:, 1], -ab[:, 0]], axis=1) / length[:, None]
    offset = np.einsum("kj,kj->k", normal, a)
    return (points @ normal.T - offset[None]).max(axis=1)


def _hull_polygon(points_xz: np.ndarray) -> np.ndarray | None:
    from scipy.spatial import ConvexHull, QhullError

    if len(points_xz) < 3:
        return None
    try:
        hull = ConvexHull(points_xz)
    except QhullError:
        return None
    return points_xz[hull.vertices]  # counter-clockwise for 2D input


def _hull_distance(body, landmarks: BodyLandmarks, hull: HullSpec, origin: np.ndarray, spacing: float,
                   shape: tuple[int, int, int]) -> np.ndarray:
    """Distance [m] (nx, ny, nz) to the horizontal hulls, faded to +large above ``hull.top_y``."""
    v = np.asarray(body.v_template, dtype=np.float64)
    edges = body_edges(body.faces)
    arm_weight = np.asarray(body.weights)[:, list(_ARM_JOINTS)].sum(axis=1, keepdims=True)
    nx, ny, nz = shape
    xs = origin[0] + spacing * np.arange(nx)
    zs = origin[2] + spacing * np.arange(nz)
    grid_xz = np.stack(np.meshgrid(xs, zs, indexing="ij"), axis=-1).reshape(-1, 2)
    far = 10.0
    out = np.full(shape, far, dtype=np.float64)
    above = None  # the hull of the section above, carried down when draping
    for j in range(ny - 1, -1, -1):  # top to bottom
        y = origin[1] + spacing * j
        if y >= hull.top_y:
            continue
        pts, aw = horizontal_section(v, edges, y, weights=arm_weight)
        pts = pts[aw[:, 0] < 0.5][:, [0, 2]]
        if hull.drape_below_y is not None and y < hull.drape_below_y and above is not None:
            pts = np.vstack([pts, above])
        if len(pts) < 3:
            continue
        if hull.per_leg_below_y is not None and y < hull.per_leg_below_y:
            groups = [pts[pts[:, 0] >= landmarks.center_x], pts[pts[:, 0] < landmarks.center_x]]
        else:
            groups = [pts]
        d = np.full(len(grid_xz), far)
        for group in groups:
            poly = _hull_polygon(group)
            if poly is not None:
                d = np.minimum(d, _convex_polygon_distance(grid_xz, poly))
                above = poly
        # Fade: a growing penalty hands the cover back to the body near top_y, without a step.
        fade = smoothstep((y - (hull.top_y - hull.fade)) / hull.fade)
        out[:, j, :] = (d + fade * 0.2).reshape(nx, nz)
    return out


def envelope_field(body, box: np.ndarray, spacing: float, ease: Callable[[np.ndarray], np.ndarray], *,
                   hull: HullSpec | None = None, landmarks: BodyLandmarks | None = None,
                   blur: float = 0.005) -> EnvelopeGrid:
    """Sample F = d_C - ease on a grid over ``box``.

    body: a BodyModel (its rest template ``v_template``, ``faces``, ``weights`` are used).
    box [m], shape (2, 3): min and max corner of the region the garment lies in (with margin).
    spacing [m]: the marching-cubes grid spacing h (the exact body distance is sampled at 2h).
    ease: maps points [m] (N, 3) to the ease [m] (N,) at each.
    hull: horizontal hulls joining the cover (None: the body alone).
    blur [m]: standard deviation of the Gaussian applied to F.
    Returns an :class:`EnvelopeGrid`; its border samples are set outside (positive).
    """
    from scipy.ndimage import gaussian_filter, map_coordinates

    from simgen.body.surface import project_to_surface

    box = np.asarray(box, dtype=np.float64)
    if landmarks is None:
        landmarks = body_landmarks(body)
    shape = tuple(int(np.ceil((box[1, i] - box[0, i]) / spacing)) + 1 for i in range(3))
    origin = box[0]
    # Exact signed distance on the coarse grid (every other fine sample, plus one beyond the end).
    coarse_shape = tuple((n + 2) // 2 + 1 for n in shape)
    axes = [origin[i] + 2.0 * spacing * np.arange(coarse_shape[i]) for i in range(3)]
    coarse_points = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    sd = project_to_surface(coarse_points, body.v_template, body.faces).signed_distance.reshape(coarse_shape)
    fine_index = [0.5 * np.arange(n) for n in shape]
    coords = np.stack(np.meshgrid(*fine_index, indexing="ij"), axis=0).reshape(3, -1)
    d_body = map_coordinates(sd, coords, order=3, mode="nearest").reshape(shape)
    cover = d_body
    if hull is not None:
        cover = np.minimum(d_body, _hull_distance(body, landmarks, hull, origin, spacing, shape))
    grid = EnvelopeGrid(origin=origin, spacing=float(spacing), values=np.empty(shape))
    points = grid.points()
    values = cover - ease(points).reshape(shape)
    if hull is not None and hull.leg_gap_below_y is not None:
        # Positive inside the slab |x - cx| < gap below the crotch seam: max() makes it outside.
        # A slab thinner than the grid would be blurred away: at least 0.75 h.
        gap = max(hull.leg_gap, 0.75 * spacing)
        slab = np.minimum(gap - np.abs(points[:, 0] - landmarks.center_x), hull.leg_gap_below_y - points[:, 1])
        values = np.maximum(values, slab.reshape(shape))
    # The blur removes the creases of the union; its width is fixed in metres (a blur of one
    # coarse voxel would close gaps of a few centimetres, e.g. between the legs).
    values = gaussian_filter(values, sigma=blur / spacing, mode="nearest")
    border = np.zeros(shape, dtype=bool)
    border[[0, -1], :, :] = True
    border[:, [0, -1], :] = True
    border[:, :, [0, -1]] = True
    values[border] = spacing
    grid.values = values
    return grid


def envelope_surface(grid: EnvelopeGrid) -> tuple[np.ndarray, np.ndarray]:
    """Marching cubes of F = 0: the largest closed component, outward oriented.

    Returns vertices [m] (V, 3) and faces (F, 3), counter-clockwise seen from outside.
    """
    from skimage.measure import marching_cubes

    from simgen.garment.mesh import connected_components

    verts, faces, _, _ = marching_cubes(grid.values, level=0.0, spacing=(grid.spacing,) * 3)
    verts = verts.astype(np.float64) + grid.origin
    faces = faces.astype(np.int64)
    n, labels = connected_components(faces, len(verts))
    if n > 1:
        largest = np.bincount(labels[faces[:, 0]]).argmax()
        faces = faces[labels[faces[:, 0]] == largest]
    used = np.unique(faces)
    remap = np.full(len(verts), -1, dtype=np.int64)
    remap[used] = np.arange(len(used))
    verts, faces = verts[used], remap[faces]
    if _signed_volume(verts, faces) < 0.0:
        faces = faces[:, ::-1].copy()
    return verts, faces


def _signed_volume(vertices: np.ndarray, faces: np.ndarray) -> float:
    a, b, c = (vertices[faces[:, i]] for i in range(3))
    return float(np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6.0)
