"""Quality measures of simulated garment frames: membrane strain and depth inside the posed body.

Both are computed here from positions alone (numpy + the body's surface query), independently of
the solver's own statistics, so :mod:`simgen.dataset.check` can audit a store.
"""

from __future__ import annotations

import numpy as np

__all__ = ["triangle_rest_inverse", "triangle_strain", "strain_summary", "body_penetration", "DEFAULT_MAX_STRAIN"]

DEFAULT_MAX_STRAIN = 1.0  # [-] largest principal stretch - 1 of a healthy frame (the check's limit, the retry's trigger)


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
    x = np.asarray(positions, dtype=np.float64)
    single = x.ndim == 2
    if single:
        x = x[None]
    f = np.asarray(faces, dtype=np.int64)
    Ds = np.stack([x[:, f[:, 1]] - x[:, f[:, 0]], x[:, f[:, 2]] - x[:, f[:, 0]]], axis=-1)  # (T, F, 3, 2)
    F = Ds @ rest_inverse[None]
    a = np.einsum("tfi,tfi->tf", F[..., 0], F[..., 0])
    b = np.einsum("tfi,tfi->tf", F[..., 0], F[..., 1])
    c = np.einsum("tfi,tfi->tf", F[..., 1], F[..., 1])
    lam = 0.5 * (a + c) + np.sqrt(np.maximum(0.25 * (a - c) ** 2 + b * b, 0.0))
    s = np.sqrt(lam) - 1.0
    return s[0] if single else s


def strain_summary(positions, faces, rest_inverse) -> tuple[np.ndarray, np.ndarray]:
    """Per-frame mean and max of :func:`triangle_strain`: two arrays of shape (T,)."""
    s = triangle_strain(positions, faces, rest_inverse)
    if s.ndim == 1:
        s = s[None]
    return s.mean(axis=1), s.max(axis=1)


def body_penetration(points, body_vertices, body_faces, *, probe: float = 2.0e-3, device: str = "cpu",
                     home_parts=None, part_masks=None, pinch_distance: float = 5.0e-3
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Depth [m] of cloth vertices inside the posed body, which are at a body self-intersection, and
    every vertex's distance to the body.

    points (V, 3) cloth vertices [m]; body_vertices (Vb, 3) posed body [m]; body_faces (Fb, 3).
    Returns depth (V,) (0 outside; signed distance by the winding number), self_hit (V,) bool and
    distance (V,) [m] (the unsigned distance to the body surface); self_hit is
    an inside vertex whose closest body point, moved ``probe`` outward along the surface normal,
    is still inside the body (the closest surface is buried in another body part, as in the
    armpits and crotch); or, given home_parts (V,) (each vertex's body part,
    :func:`simgen.body.parts.vertex_parts` of the garment's weights) and part_masks (Fb,)
    (:func:`simgen.body.parts.face_part_masks`), an inside vertex lying outside its own part
    within ``pinch_distance`` [m] of it: cloth the solver's contact keeps on its own part where
    another part presses into it. The same rules as the solver's statistics, computed here
    independently.
    """
    from simgen.body.surface import project_to_surface

    proj = project_to_surface(points, body_vertices, body_faces, device=device)
    depth = np.where(proj.signed_distance < 0.0, -proj.signed_distance, 0.0)
    self_hit = np.zeros(len(depth), dtype=bool)
    inside = np.nonzero(depth > 0)[0]
    if len(inside):
        bv = np.asarray(body_vertices, dtype=np.float64)
        bf = np.asarray(body_faces)
        tri = bv[bf[proj.face[inside]]]
        n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-30)
        outward = proj.closest[inside] + probe * n
        sd = project_to_surface(outward, bv, bf, device=device).signed_distance
        self_hit[inside] = sd < 0.0
    rest = inside[~self_hit[inside]]
    if len(rest) and home_parts is not None and part_masks is not None:
        pts = np.asarray(points, dtype=np.float64)
        home = np.asarray(home_parts)[rest]
        masks = np.asarray(part_masks)
        for part in np.unique(home):
            sel = rest[home == part]
            faces = bf[(masks & (1 << int(part))) != 0]
            own = project_to_surface(pts[sel], bv, faces, device=device)
            tri = bv[faces[own.face]]
            n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
            offset = pts[sel] - own.closest
            outside_own = np.einsum("ij,ij->i", offset, n) >= 0.0
            self_hit[sel] = outside_own & (np.linalg.norm(offset, axis=1) <= pinch_distance)
    return depth, self_hit, np.abs(proj.signed_distance)
