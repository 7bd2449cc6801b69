"""Closest-point and signed-distance queries against a body surface (Warp BVH, CPU or GPU).

Used to check garments against the template body (no vertex inside, clearance >= 2 mm), to compute
skinning weights from the closest body triangle, and by the collision post-process.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from simgen.errors import InputError

__all__ = ["SurfaceProjection", "project_to_surface", "vertex_normals"]


@dataclass
class SurfaceProjection:
    """Closest points of query points on a triangle mesh.

    signed_distance [m], shape (P,): negative inside the surface (generalised winding number > 0.5);
    closest [m], shape (P, 3); face, shape (P,): index of the closest triangle; bary, shape (P, 3):
    barycentric weights of that triangle's three vertices (closest = bary @ vertices[faces[face]]).
    """

    signed_distance: np.ndarray
    closest: np.ndarray
    face: np.ndarray
    bary: np.ndarray


def project_to_surface(points, vertices, faces, *, device: str | None = "cpu") -> SurfaceProjection:
    """Project points onto a closed triangle mesh and classify them inside/outside.

    points [m], shape (P, 3); vertices [m], shape (V, 3); faces, shape (F, 3).
    The sign uses the winding number, robust on a watertight mesh and a smooth approximation where
    a posed body intersects itself. Computation in float32 (Warp), results returned as float64.
    """
    import warp as wp

    from simgen.body import _surface_kernels as kernels

    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    vertices = np.asarray(vertices, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64)
    if not np.all(np.isfinite(points)):
        raise InputError("points to project contain NaN or inf")
    n = len(points)
    if n == 0:
        return SurfaceProjection(np.zeros(0), np.zeros((0, 3)), np.zeros(0, dtype=np.int64), np.zeros((0, 3)))
    wp.config.quiet = True
    wp.init()
    mesh = wp.Mesh(
        points=wp.array(vertices, dtype=wp.vec3, device=device),
        indices=wp.array(faces.reshape(-1).astype(np.int32), dtype=wp.int32, device=device),
        support_winding_number=True,
    )
    extent = float(np.linalg.norm(np.ptp(np.vstack([vertices, points]), axis=0))) + 1.0
    sd = wp.zeros(n, dtype=float, device=device)
    closest = wp.zeros(n, dtype=wp.vec3, device=device)
    face = wp.zeros(n, dtype=wp.int32, device=device)
    bary = wp.zeros(n, dtype=wp.vec3, device=device)
    wp.launch(kernels.closest_point_kernel, dim=n,
              inputs=[mesh.id, wp.array(points, dtype=wp.vec3, device=device), extent],
              outputs=[sd, closest, face, bary], device=device)
    return SurfaceProjection(
        signed_distance=sd.numpy().astype(np.float64),
        closest=closest.numpy().astype(np.float64),
        face=face.numpy().astype(np.int64),
        bary=bary.numpy().astype(np.float64),
    )


def vertex_normals(vertices, faces) -> np.ndarray:
    """Area-weighted unit vertex normals of a triangle mesh (outward for counter-clockwise faces).

    vertices [m], shape (V, 3); faces, shape (F, 3). Returns (V, 3) float64; a vertex of no face
    gets the zero vector.
    """
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    fn = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    vn = np.zeros_like(v)
    for k in range(3):
        np.add.at(vn, f[:, k], fn)
    return vn / np.maximum(np.linalg.norm(vn, axis=1, keepdims=True), 1e-300)
