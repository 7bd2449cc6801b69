"""Closest points, signed distances and inside/outside of points on a closed triangle mesh (a body).

The query is the body-surface query of :mod:`simgen.body.surface_query` (its specification: the
closest face by Warp's BVH, the exact closest point recomputed in float64 on the given float64
vertices, the sign by the winding number or the pseudo-normal), run by Warp on the CPU or a GPU.
The winding-number sign (the default) is the audit's: garment checks against the template body (no
vertex inside, clearance >= 2 mm), skinning weights from the closest body triangle, remeshing onto
the body, motion clearance, and the dataset check and learned-model evaluation on posed bodies.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from simgen.errors import InputError

__all__ = ["SIGNS", "SurfaceProjection", "SurfaceMesh", "project_to_surface", "vertex_normals"]

#: Sign variants of the query (:mod:`simgen.body.surface_query`): name -> its ``winding`` argument.
SIGNS = {"winding": 1, "normal": 0}


@dataclass
class SurfaceProjection:
    """Closest points of query points on a triangle mesh (float64).

    signed_distance [m], shape (P,): negative inside (the sign variant's; the query distance where
    no face is that close); closest [m], shape (P, 3); normal, shape (P, 3): the outward unit
    normal, grad of the signed distance (closest = point - signed_distance * normal); face, shape
    (P,): index of the closest triangle (-1 where none); bary, shape (P, 3): barycentric weights of
    that triangle's three vertices (closest = bary @ vertices[faces[face]]).
    """

    signed_distance: np.ndarray
    closest: np.ndarray
    normal: np.ndarray
    face: np.ndarray
    bary: np.ndarray


class SurfaceMesh:
    """A closed triangle mesh on a Warp device, built once for repeated queries.

    vertices [m], shape (V, 3); faces, shape (F, 3) (counter-clockwise seen from outside for the
    pseudo-normal sign); device: Warp device ("cpu", "cuda:0", None: Warp's default). The BVH is
    float32 (it only picks the closest face and the sign); distances are float64 on ``vertices``.
    """

    def __init__(self, vertices, faces, *, device: str | None = "cpu") -> None:
        import warp as wp

        from simgen._warp_log import init_warp

        init_warp(device)
        v = np.asarray(vertices, dtype=np.float64)
        f = np.asarray(faces, dtype=np.int32)
        if v.ndim != 2 or v.shape[1] != 3 or f.ndim != 2 or f.shape[1] != 3 or len(f) == 0:
            raise InputError(f"a surface needs vertices (V, 3) and faces (F, 3), got {v.shape} and {f.shape}")
        self.device = device
        self.bounds = (v.min(axis=0), v.max(axis=0))
        self.vertices = wp.array(v, dtype=wp.vec3d, device=device)
        self.faces = wp.array(f, dtype=wp.int32, device=device)
        self.points = wp.array(v, dtype=wp.vec3, device=device)
        self.mesh = wp.Mesh(points=self.points, indices=wp.array(f.reshape(-1), dtype=wp.int32, device=device),
                            support_winding_number=True)

    def project(self, points, *, sign: str = "winding") -> SurfaceProjection:
        """Closest points of ``points`` [m], shape (P, 3), with the sign variant ``sign`` ("winding"
        or "normal", :data:`SIGNS`). Every point finds its face (the query reaches the whole mesh)."""
        import warp as wp

        from simgen.body.surface_query import query_kernel

        if sign not in SIGNS:
            raise InputError(f"sign must be one of {', '.join(SIGNS)}, got {sign!r}")
        p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        if not np.all(np.isfinite(p)):
            raise InputError("points to project contain NaN or inf")
        n = len(p)
        if n == 0:
            return SurfaceProjection(np.zeros(0), np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0, dtype=np.int64),
                                     np.zeros((0, 3)))
        lo, hi = np.minimum(self.bounds[0], p.min(axis=0)), np.maximum(self.bounds[1], p.max(axis=0))
        reach = float(np.linalg.norm(hi - lo)) + 1.0
        dev = self.device
        out = [wp.empty(n, dtype=wp.float64, device=dev), wp.empty(n, dtype=wp.vec3d, device=dev),
               wp.empty(n, dtype=wp.vec3d, device=dev), wp.empty(n, dtype=wp.int32, device=dev),
               wp.empty(n, dtype=wp.vec3d, device=dev)]
        wp.launch(query_kernel(wp.float64), dim=n, device=dev,
                  inputs=[self.mesh.id, self.vertices, self.faces, wp.array(p, dtype=wp.vec3d, device=dev), reach,
                          SIGNS[sign]], outputs=out)
        d, normal, closest, face, bary = (a.numpy() for a in out)
        return SurfaceProjection(signed_distance=d, closest=closest, normal=normal, face=face.astype(np.int64),
                                 bary=bary)


def project_to_surface(points, vertices, faces, *, sign: str = "winding", device: str | None = "cpu"
                       ) -> SurfaceProjection:
    """Project points onto a closed triangle mesh and classify them inside/outside (float64).

    points [m], shape (P, 3); vertices [m], shape (V, 3); faces, shape (F, 3); sign: "winding" (the
    generalised winding number: robust on a watertight mesh and where a posed body intersects
    itself) or "normal" (the pseudo-normal of the closest feature, the solver's). One-off: builds a
    :class:`SurfaceMesh` (keep one to query the same mesh repeatedly).
    """
    return SurfaceMesh(vertices, faces, device=device).project(points, sign=sign)


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
