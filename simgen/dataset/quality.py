"""Quality measures of simulated garment frames: membrane strain and depth inside the posed body.

Both are computed here from positions alone (numpy, and the body-surface query with the
statistics' own rules, :mod:`simgen.body.surface_query`), independently of the statistics the
solver stored, so :mod:`simgen.dataset.check` can audit a store.
"""

from __future__ import annotations

import numpy as np

__all__ = ["triangle_rest_inverse", "triangle_strain", "strain_summary", "body_penetration",
           "penetration_rule", "DEFAULT_MAX_STRAIN", "DEFAULT_MAX_DEPTH"]

DEFAULT_MAX_STRAIN = 1.0  # [-] largest principal stretch - 1 of a healthy frame (the check's limit, the retry's trigger)
DEFAULT_MAX_DEPTH = 1.0e-3  # [m] the solver's contract: no vertex more than 1 mm inside (self-intersections apart)
STRAIN_CHUNK_FRAMES = 8   # frames per pass of triangle_strain (its temporaries stay a few MB)


def triangle_rest_inverse(rest, faces) -> np.ndarray:
    """Inverse rest shape matrices Dm^-1 (F, 2, 2) of triangles laid out in their own 2D frames.

    rest [m], shape (V, 3): the cloth's stress-free shape (the garment template); faces (F, 3).
    """
    x = np.asarray(rest, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    e1 = x[f[:, 1]] - x[f[:, 0]]
    e2 = x[f[:, 2]] - x[f[:, 0]]
    l1 = np.linalg.norm(e1, axis=1)
    n = np.linalg.norm(np.cross(e1, e2), axis=1)
    Dm = np.zeros((len(f), 2, 2))
    Dm[:, 0, 0] = l1
    Dm[:, 0, 1] = np.einsum("ij,ij->i", e1, e2) / np.maximum(l1, 1e-30)
    Dm[:, 1, 1] = n / np.maximum(l1, 1e-30)
    return np.linalg.inv(Dm)


def triangle_strain(positions, faces, rest_inverse) -> np.ndarray:
    """Largest principal stretch minus one of every triangle (engineering strain, 0 = rest length).

    positions [m], shape (T, V, 3) or (V, 3); faces (F, 3); rest_inverse (F, 2, 2) from
    :func:`triangle_rest_inverse`. Returns shape (T, F) (or (F,)): sqrt(largest eigenvalue of
    F^T F) - 1 with F = Ds Dm^-1 the (3 x 2) deformation gradient.
    """
    x = np.asarray(positions)
    single = x.ndim == 2
    if single:
        x = x[None]
    f = np.asarray(faces, dtype=np.int64)
    r = np.asarray(rest_inverse, dtype=np.float64)
    r00, r01, r10, r11 = (r[:, i, j, None] for i, j in ((0, 0), (0, 1), (1, 0), (1, 1)))
    out = np.empty((len(x), len(f)))
    # A few frames at a time, in float64, with the two columns of F = [e1 e2] Dm^-1 written out
    # (a batched 3x2 @ 2x2 matmul over every triangle of a whole sequence was about 3x slower: BENCHMARKS.md).
    for t in range(0, len(x), STRAIN_CHUNK_FRAMES):
        xs = x[t:t + STRAIN_CHUNK_FRAMES].astype(np.float64)
        p0 = xs[:, f[:, 0]]
        e1, e2 = xs[:, f[:, 1]] - p0, xs[:, f[:, 2]] - p0                     # (t, F, 3)
        F0, F1 = e1 * r00 + e2 * r10, e1 * r01 + e2 * r11                      # F's columns
        a = np.einsum("tfi,tfi->tf", F0, F0)
        b = np.einsum("tfi,tfi->tf", F0, F1)
        c = np.einsum("tfi,tfi->tf", F1, F1)
        lam = 0.5 * (a + c) + np.sqrt(np.maximum(0.25 * (a - c) ** 2 + b * b, 0.0))
        out[t:t + STRAIN_CHUNK_FRAMES] = np.sqrt(lam) - 1.0
    return out[0] if single else out


def strain_summary(positions, faces, rest_inverse) -> tuple[np.ndarray, np.ndarray]:
    """Per-frame mean and max of :func:`triangle_strain`: two arrays of shape (T,)."""
    s = triangle_strain(positions, faces, rest_inverse)
    if s.ndim == 1:
        s = s[None]
    return s.mean(axis=1), s.max(axis=1)


def penetration_rule(skin_weights, body, solver: dict | None = None) -> dict:
    """The keyword arguments of :func:`body_penetration` that make it count like the solver's
    statistics and ``simgen dataset check``: home_parts (V,) from the garment's skinning weights
    (V, 24), part_masks (Fb,) of ``body`` (a BodyModel) and the pinch distance [m] of the store's
    solver (``attrs["solver"]``: its "config", or the dict itself where it has none; the default
    ContactParams' without one). Without skinning weights (None) the body part rule is off
    (home_parts and part_masks None)."""
    from simgen.body.parts import face_part_masks, face_parts, vertex_parts
    from simgen.params import ContactParams

    solver = solver or {}
    contact = (solver.get("config", solver) or {}).get("contact") or {}
    pinch = float(contact.get("pinch_distance", ContactParams.pinch_distance))
    if skin_weights is None:
        return {"home_parts": None, "part_masks": None, "pinch_distance": pinch}
    return {"home_parts": vertex_parts(np.asarray(skin_weights)),
            "part_masks": face_part_masks(body.v_template, body.faces, face_parts(body.weights, body.faces)),
            "pinch_distance": pinch}


def body_penetration(points, body_vertices, body_faces, *, probe: float | None = None, device: str = "cpu",
                     home_parts=None, part_masks=None, pinch_distance: float = 5.0e-3
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Depth [m] of cloth vertices inside the posed body, which are at a body self-intersection, and
    every vertex's distance to the body.

    points (V, 3) cloth vertices [m]; body_vertices (Vb, 3) posed body [m]; body_faces (Fb, 3);
    probe [m]: the self-intersection probe (None: :data:`simgen.body.surface_query.SELF_INTERSECTION_PROBE`,
    the statistics' own); home_parts (V,) (each vertex's body part, :func:`simgen.body.parts.vertex_parts` of
    the garment's weights) and part_masks (Fb,) (:func:`simgen.body.parts.face_part_masks`),
    optional, switch on the body part rule; pinch_distance [m]. Returns depth (V,) (0 outside;
    inside by the winding number), self_hit (V,) bool and distance (V,) [m] (the unsigned distance
    to the body surface). The rules are the solver statistics' own, the same Warp kernel
    (:data:`simgen.body.surface_query.classify_inside`), run here on positions alone.
    """
    import warp as wp

    from simgen.body.surface import SurfaceMesh
    from simgen.body.surface_query import SELF_INTERSECTION_PROBE, classify_inside

    x = np.asarray(points, dtype=np.float32).reshape(-1, 3)
    surface = SurfaceMesh(body_vertices, body_faces, device=device)
    n = len(x)
    use_parts = home_parts is not None and part_masks is not None
    parts = [wp.array(np.asarray(a, dtype=np.int32), dtype=wp.int32, device=device) if use_parts else None
             for a in (home_parts, part_masks)]
    reach = float(np.linalg.norm(np.ptp(np.vstack([np.asarray(body_vertices, dtype=np.float64), x]), axis=0))) + 1.0
    out = [wp.zeros(n, dtype=wp.float32, device=device), wp.zeros(n, dtype=wp.float32, device=device),
           wp.zeros(n, dtype=wp.int32, device=device), wp.zeros(n, dtype=wp.int32, device=device)]
    wp.launch(classify_inside, dim=n, device=device, inputs=[
        wp.array(x, dtype=wp.vec3, device=device), wp.zeros(n, dtype=wp.int32, device=device),
        wp.array([surface.mesh.id], dtype=wp.uint64, device=device), reach,
        SELF_INTERSECTION_PROBE if probe is None else float(probe), parts[0], parts[1],
        int(use_parts), float(pinch_distance)], outputs=out)
    distance, depth, _, self_hit = (a.numpy() for a in out)
    return depth.astype(np.float64), self_hit != 0, distance.astype(np.float64)
