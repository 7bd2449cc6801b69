"""Small synthetic bodies and garments for the garment tests (imported by tests/test_garment_*.py).

``two_leg_body()`` is a watertight SMPL-format body of three closed tubes: a torso and two legs,
Y-up, metres, facing +Z, the body's left on +X, mirror-symmetric about x = 0 (vertex positions and
weights; left and right joints swap). Skinning weights are piecewise-linear "hat" functions of
height along each limb's joint chain, so they vary smoothly on each tube and are exactly known at
every vertex. Two shape components: beta 0 stretches the body vertically, beta 1 thickens the limbs.
"""

from __future__ import annotations

import numpy as np

from simgen.body import SMPL_JOINT_NAMES, SMPL_PARENTS, BodyModel

J = {name: i for i, name in enumerate(SMPL_JOINT_NAMES)}
LEFT_LEG = [J["left_hip"], J["left_knee"], J["left_ankle"], J["left_foot"]]
RIGHT_LEG = [J["right_hip"], J["right_knee"], J["right_ankle"], J["right_foot"]]

LEG_X = 0.09  # [m] leg axes at x = +-LEG_X
LEG_R = 0.065  # [m] leg radius: 5 cm between the legs
TORSO_R = 0.16


def tube(cx: float, cz: float, y0: float, y1: float, radius: float, n_around: int, n_rings: int,
         capped: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """A tube along +Y (rings of n_around vertices at n_rings heights), capped by two fans when
    ``capped`` (then closed and outward oriented), else open at both ends. Returns (vertices, faces)."""
    theta = 2 * np.pi * np.arange(n_around) / n_around
    ys = np.linspace(y0, y1, n_rings)
    ring = np.stack([cx + radius * np.cos(theta), np.zeros(n_around), cz + radius * np.sin(theta)], axis=1)
    verts = [ring + np.array([0.0, y, 0.0]) for y in ys]
    v = np.concatenate(verts)
    faces = []
    for r in range(n_rings - 1):
        for k in range(n_around):
            a, b = r * n_around + k, r * n_around + (k + 1) % n_around
            c, d = a + n_around, b + n_around
            # Counter-clockwise seen from outside (normal pointing away from the axis).
            faces += [[a, c, b], [b, c, d]]
    if capped:
        bottom, top = len(v), len(v) + 1
        v = np.concatenate([v, [[cx, y0, cz], [cx, y1, cz]]])
        last = (n_rings - 1) * n_around
        for k in range(n_around):
            faces.append([bottom, k, (k + 1) % n_around])
            faces.append([top, last + (k + 1) % n_around, last + k])
    return v, np.asarray(faces, dtype=np.int64)


def _hat_weights(y: np.ndarray, heights: list[float], joints: list[int]) -> np.ndarray:
    """Piecewise-linear interpolation between joints placed at the given heights (clamped)."""
    order = np.argsort(heights)
    h = np.asarray(heights)[order]
    js = np.asarray(joints)[order]
    w = np.zeros((len(y), 24))
    for k, j in enumerate(js):
        e = np.zeros(len(h))
        e[k] = 1.0
        w[:, j] += np.interp(y, h, e)
    return w


def two_leg_body(n_around: int = 24, torso_rings: int = 12, leg_rings: int = 18) -> BodyModel:
    """The synthetic body of the module docstring (~1.6k vertices)."""
    parts = [
        ("torso", tube(0.0, 0.0, 0.80, 1.50, TORSO_R, n_around, torso_rings)),
        ("left", tube(LEG_X, 0.0, 0.00, 0.88, LEG_R, n_around, leg_rings)),
        ("right", tube(-LEG_X, 0.0, 0.00, 0.88, LEG_R, n_around, leg_rings)),
    ]
    verts, faces, weights, part_of = [], [], [], []
    offset = 0
    for name, (v, f) in parts:
        if name == "torso":
            w = _hat_weights(v[:, 1], [0.90, 1.04, 1.17, 1.30, 1.45],
                             [J["pelvis"], J["spine1"], J["spine2"], J["spine3"], J["neck"]])
        else:
            side = "left" if name == "left" else "right"
            w = _hat_weights(v[:, 1], [0.95, 0.80, 0.47, 0.07],
                             [J["pelvis"], J[f"{side}_hip"], J[f"{side}_knee"], J[f"{side}_ankle"]])
        verts.append(v)
        faces.append(f + offset)
        weights.append(w)
        part_of += [name] * len(v)
        offset += len(v)
    v = np.concatenate(verts)
    f = np.concatenate(faces)
    w = np.concatenate(weights)
    part_of = np.asarray(part_of)

    # Joints on the tube axes, regressed from the ring nearest to each joint's height.
    joint_at = {
        "pelvis": ("torso", 0.90), "left_hip": ("left", 0.80), "right_hip": ("right", 0.80),
        "spine1": ("torso", 1.04), "left_knee": ("left", 0.47), "right_knee": ("right", 0.47),
        "spine2": ("torso", 1.17), "left_ankle": ("left", 0.07), "right_ankle": ("right", 0.07),
        "spine3": ("torso", 1.30), "left_foot": ("left", 0.02), "right_foot": ("right", 0.02),
        "neck": ("torso", 1.45), "left_collar": ("torso", 1.40), "right_collar": ("torso", 1.40),
        "head": ("torso", 1.50), "left_shoulder": ("torso", 1.40), "right_shoulder": ("torso", 1.40),
        "left_elbow": ("torso", 1.40), "right_elbow": ("torso", 1.40), "left_wrist": ("torso", 1.40),
        "right_wrist": ("torso", 1.40), "left_hand": ("torso", 1.40), "right_hand": ("torso", 1.40),
    }
    J_regressor = np.zeros((24, len(v)))
    ring_ys = {name: np.unique(np.round(p[0][: -2, 1], 9)) for name, p in parts}
    for jname, (part, y) in joint_at.items():
        ys = ring_ys[part]
        y_ring = ys[np.argmin(np.abs(ys - y))]
        members = np.flatnonzero((part_of == part) & (np.abs(v[:, 1] - y_ring) < 1e-9))
        J_regressor[J[jname], members] = 1.0 / len(members)

    # beta 0: +3 % height per unit; beta 1: +1 cm radius per unit (axis-centred, caps' centres fixed).
    shapedirs = np.zeros((len(v), 3, 2))
    shapedirs[:, 1, 0] = 0.03 * v[:, 1]
    axis_x = np.select([part_of == "left", part_of == "right"], [LEG_X, -LEG_X], 0.0)
    radial = np.stack([v[:, 0] - axis_x, np.zeros(len(v)), v[:, 2]], axis=1)
    length = np.linalg.norm(radial, axis=1, keepdims=True)
    shapedirs[:, :, 1] = np.where(length > 1e-9, 0.01 * radial / np.maximum(length, 1e-12), 0.0)

    return BodyModel(v, shapedirs, np.zeros((len(v), 3, 0)), J_regressor, w, SMPL_PARENTS, f, name="twoleg")


def skirt(radius: float = 0.20, y0: float = 0.45, y1: float = 0.85, n_around: int = 32,
          n_rings: int = 9) -> tuple[np.ndarray, np.ndarray]:
    """An open tube around both legs (a straight skirt), vertices (V, 3) and faces (F, 3)."""
    return tube(0.0, 0.0, y0, y1, radius, n_around, n_rings, capped=False)


def left_right(weights: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Total weight on the left and on the right leg joints, each shape (V,)."""
    return weights[:, LEFT_LEG].sum(axis=1), weights[:, RIGHT_LEG].sum(axis=1)


def brute_force_closest(vertices: np.ndarray, faces: np.ndarray, points: np.ndarray):
    """Closest surface points by exhaustive search over all triangles (trimesh's point-triangle
    routine, no BVH): closest (P, 3), distance (P,), triangle (P,), barycentric (P, 3)."""
    import trimesh

    tris = vertices[faces]
    best = np.full(len(points), np.inf)
    tri = np.zeros(len(points), dtype=np.int64)
    closest = np.zeros((len(points), 3))
    for i, p in enumerate(points):
        c = trimesh.triangles.closest_point(tris, np.broadcast_to(p, (len(tris), 3)))
        d = np.linalg.norm(c - p, axis=1)
        k = int(np.argmin(d))
        best[i], tri[i], closest[i] = d[k], k, c[k]
    bary = trimesh.triangles.points_to_barycentric(tris[tri], closest)
    return closest, best, tri, bary
