"""Collision post-process of predicted garments (thesis ch. 4, Fig. 4.3), in torch.

After skinning, garment vertices that ended inside the body (or closer to it than a clearance) are
pushed out of their closest body primitive until they are ``clearance`` [m] outside. The thesis
gives no distance; 2 mm is the value in the authors' released code, which moves a vertex along the
normal of its nearest body *vertex*. Here the closest point c is on the nearest *triangle*, and a
vertex x with signed distance s < clearance moves to c + clearance n, n the outward unit direction
of the distance field at x: (x - c) / |x - c| outside, its opposite inside, the face normal when x
is on the surface. That is the face normal wherever c is inside a triangle, and the exact direction
away from an edge or a corner elsewhere; the vertex ends exactly ``clearance`` from that primitive.

Two ways to find the closest triangle and the sign (``BodySurface(backend=...)``):

- ``"warp"`` (the default when warp-lang imports): Warp's BVH query ``mesh_query_point_sign_normal``
  (sign from the angle-weighted pseudo-normal of the closest feature, robust on a watertight body)
  on a ``wp.Mesh`` built once and refit for every frame, on the tensors' device (CPU or CUDA, on
  torch's stream, memory shared through ``wp.from_torch``);
- ``"torch"`` (no Warp needed, any torch device): the k body vertices nearest to each garment
  vertex (a chunked ``torch.cdist`` + ``topk``) name the candidate triangles (all triangles around
  those vertices), the exact point-triangle distance (Ericson, *Real-Time Collision Detection*,
  5.1.5) picks the closest, and the sign comes from the barycentric blend of area-weighted vertex
  normals at c; brute force, ~10x slower on the CPU.

``tests/test_learn_collision.py`` holds both equal to each other and to the winding-number query of
:func:`simgen.body.surface.project_to_surface`.
"""

from __future__ import annotations

import contextlib
from dataclasses import dataclass

import numpy as np
import torch

from simgen.errors import InputError

__all__ = ["DEFAULT_CLEARANCE", "BACKENDS", "SurfaceQuery", "BodySurface", "closest_point_on_triangles", "push_out"]

BACKENDS = ("auto", "warp", "torch")

#: Distance [m] outside the body at which the post-process leaves colliding vertices (authors' code).
DEFAULT_CLEARANCE = 0.002


def closest_point_on_triangles(p: torch.Tensor, a: torch.Tensor, b: torch.Tensor, c: torch.Tensor) -> torch.Tensor:
    """Barycentric coordinates of the closest point of each triangle (a, b, c) to p.

    All arguments [m] of shape (..., 3) (broadcastable). Returns shape (..., 3), non-negative,
    summing to 1 (Voronoi-region tests in Ericson's order; the first region that holds wins).
    """
    tiny = torch.finfo(p.dtype).tiny
    ab, ac, ap = b - a, c - a, p - a
    d1, d2 = (ab * ap).sum(-1), (ac * ap).sum(-1)
    bp = p - b
    d3, d4 = (ab * bp).sum(-1), (ac * bp).sum(-1)
    cp = p - c
    d5, d6 = (ab * cp).sum(-1), (ac * cp).sum(-1)
    va, vb, vc = d3 * d6 - d5 * d4, d5 * d2 - d1 * d6, d1 * d4 - d3 * d2

    def safe_div(num, den):
        return num / torch.where(den.abs() > tiny, den, torch.full_like(den, tiny))

    # Interior (the lowest-priority region), then the regions overriding it in reverse order.
    den = va + vb + vc
    v, w = safe_div(vb, den), safe_div(vc, den)
    bary = torch.stack([1.0 - v - w, v, w], dim=-1)
    zero, one = torch.zeros_like(d1), torch.ones_like(d1)
    t_bc = safe_div(d4 - d3, (d4 - d3) + (d5 - d6))
    regions = [  # (condition, barycentrics), highest priority last
        ((va <= 0) & (d4 - d3 >= 0) & (d5 - d6 >= 0), (zero, 1.0 - t_bc, t_bc)),          # edge bc
        ((vb <= 0) & (d2 >= 0) & (d6 <= 0), (1.0 - safe_div(d2, d2 - d6), zero, safe_div(d2, d2 - d6))),  # edge ac
        ((d6 >= 0) & (d5 <= d6), (zero, zero, one)),                                        # vertex c
        ((vc <= 0) & (d1 >= 0) & (d3 <= 0), (1.0 - safe_div(d1, d1 - d3), safe_div(d1, d1 - d3), zero)),  # edge ab
        ((d3 >= 0) & (d4 <= d3), (zero, one, zero)),                                        # vertex b
        ((d1 <= 0) & (d2 <= 0), (one, zero, zero)),                                         # vertex a
    ]
    for cond, coords in regions:
        bary = torch.where(cond[..., None], torch.stack(coords, dim=-1), bary)
    return bary.clamp(0.0, 1.0)


@dataclass
class SurfaceQuery:
    """Closest points of query points on a (posed) body surface.

    signed_distance [m], shape (N, P): |x - closest|, negative inside; closest [m], shape (N, P, 3);
    normal, shape (N, P, 3): the outward unit direction of the distance field at x (see the module
    doc); face, int64 shape (N, P).
    """

    signed_distance: torch.Tensor
    closest: torch.Tensor
    normal: torch.Tensor
    face: torch.Tensor


class BodySurface:
    """The body's triangle topology, prepared once for repeated closest-point queries.

    faces, shape (F, 3) (outward counter-clockwise winding, as every simgen body); backend: "warp",
    "torch" or "auto" (warp when it imports); torch backend only: ``candidates`` = nearest body
    vertices whose incident triangles are tested exactly, ``chunk`` = query points per distance block
    (memory: chunk x V floats).
    """

    def __init__(self, faces, num_vertices: int, *, backend: str = "auto", candidates: int = 4, chunk: int = 2048,
                 device=None):
        if backend not in BACKENDS:
            raise InputError(f"collision backend {backend!r} is not one of {', '.join(BACKENDS)}")
        if backend == "auto":
            import importlib.util

            backend = "warp" if importlib.util.find_spec("warp") is not None else "torch"
        self.backend = backend
        self._meshes: dict = {}
        f = np.asarray(faces, dtype=np.int64)
        if f.ndim != 2 or f.shape[1] != 3 or len(f) == 0 or f.min() < 0 or f.max() >= num_vertices:
            raise InputError(f"body faces must have shape (F, 3) with indices below {num_vertices}")
        if candidates < 1:
            raise InputError(f"candidates must be at least 1, got {candidates}")
        self.num_vertices = int(num_vertices)
        self.candidates = int(candidates)
        self.chunk = int(chunk)
        # Vertex -> incident faces, padded with -1 to the largest valence.
        owner = f.reshape(-1)
        face_of = np.repeat(np.arange(len(f)), 3)
        order = np.argsort(owner, kind="stable")
        counts = np.bincount(owner, minlength=num_vertices)
        width = max(int(counts.max()), 1)
        start = np.concatenate([[0], np.cumsum(counts)[:-1]])
        slot = np.arange(len(owner)) - np.repeat(start, counts)
        table = np.full((num_vertices, width), -1, dtype=np.int64)
        table[owner[order], slot] = face_of[order]
        self.faces = torch.tensor(f, device=device)
        self.vertex_faces = torch.as_tensor(table, device=device)

    def to(self, device) -> "BodySurface":
        self.faces = self.faces.to(device)
        self.vertex_faces = self.vertex_faces.to(device)
        return self

    def vertex_normals(self, vertices: torch.Tensor) -> torch.Tensor:
        """Area-weighted unit vertex normals, vertices [m] (N, V, 3) -> (N, V, 3)."""
        tri = vertices[:, self.faces]  # (N, F, 3, 3)
        fn = torch.cross(tri[:, :, 1] - tri[:, :, 0], tri[:, :, 2] - tri[:, :, 0], dim=-1)
        vn = torch.zeros_like(vertices)
        for k in range(3):
            vn.index_add_(1, self.faces[:, k], fn)
        return vn / vn.norm(dim=-1, keepdim=True).clamp_min(1e-12)

    @torch.no_grad()
    def query(self, points: torch.Tensor, vertices: torch.Tensor) -> SurfaceQuery:
        """Closest body points of garment points.

        points [m], shape (N, P, 3); vertices [m] of the posed body, shape (N, V, 3) (or (V, 3) /
        (P, 3) for a single frame). Returns :class:`SurfaceQuery`.
        """
        if points.dim() == 2:
            points = points[None]
        if vertices.dim() == 2:
            vertices = vertices[None]
        if vertices.shape[1] != self.num_vertices or vertices.shape[0] != points.shape[0]:
            raise InputError(f"body vertices must have shape ({points.shape[0]}, {self.num_vertices}, 3), "
                             f"got {tuple(vertices.shape)}")
        normals = self.vertex_normals(vertices) if self.backend == "torch" else None
        n, p = points.shape[:2]
        out_sd = points.new_empty((n, p))
        out_cl = points.new_empty((n, p, 3))
        out_nr = points.new_empty((n, p, 3))
        out_fc = torch.empty((n, p), dtype=torch.int64, device=points.device)
        # The BVH query takes a whole frame at once (one refit); the brute force goes in blocks.
        chunk = self.chunk if self.backend == "torch" else max(p, 1)
        for i in range(n):
            verts = vertices[i]
            for s in range(0, p, chunk):
                x = points[i, s:s + chunk]  # (c, 3)
                if self.backend == "warp":
                    face, bary, sign = self._warp_closest(x, verts)
                else:
                    face, bary = self._torch_closest(x, verts)
                corners = verts[self.faces[face]]  # (c, 3, 3)
                c = torch.einsum("pk,pkd->pd", bary, corners)
                fn = torch.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0], dim=-1)
                fn = fn / fn.norm(dim=-1, keepdim=True).clamp_min(1e-20)
                if normals is not None:  # torch backend: the sign from the smooth normal at c
                    smooth = torch.einsum("pk,pkd->pd", bary, normals[i][self.faces[face]])
                    sign = torch.where(((x - c) * smooth).sum(-1) < 0, -1.0, 1.0).to(x.dtype)
                offset = x - c
                dist = offset.norm(dim=-1)
                on_surface = dist < 1e-9
                direction = torch.where(on_surface[:, None], fn,
                                        sign[:, None] * offset / dist.clamp_min(1e-9)[:, None])
                out_sd[i, s:s + chunk] = sign * dist
                out_cl[i, s:s + chunk] = c
                out_nr[i, s:s + chunk] = direction
                out_fc[i, s:s + chunk] = face
        return SurfaceQuery(out_sd, out_cl, out_nr, out_fc)

    def _torch_closest(self, x: torch.Tensor, verts: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Closest face (P,) int64 and barycentrics (P, 3) by brute force over candidate triangles."""
        k = min(self.candidates, self.num_vertices)
        near = torch.cdist(x, verts).topk(k, dim=1, largest=False).indices  # (c, k)
        cand = self.vertex_faces[near].reshape(len(x), -1)  # (c, k * width)
        valid = cand >= 0
        cand = cand.clamp_min(0)
        corners = verts[self.faces[cand]]  # (c, C, 3, 3)
        bary = closest_point_on_triangles(x[:, None], corners[:, :, 0], corners[:, :, 1], corners[:, :, 2])
        closest = torch.einsum("pck,pckd->pcd", bary, corners)
        d2 = ((x[:, None] - closest) ** 2).sum(-1).masked_fill(~valid, float("inf"))
        best = d2.argmin(dim=1)
        rows = torch.arange(len(x), device=x.device)
        return cand[rows, best], bary[rows, best]

    def _warp_closest(self, x: torch.Tensor, verts: torch.Tensor):
        """Closest face (P,) int64, barycentrics (P, 3) and sign (P,) (-1 inside) of points x (P, 3)
        on the mesh with vertices verts (V, 3)."""
        import warp as wp

        from simgen.learn import _collision_kernels as kernels

        wp.config.quiet = True
        wp.init()
        dev = "cpu" if x.device.type == "cpu" else f"cuda:{x.device.index or 0}"
        entry = self._meshes.get(dev)
        v32 = verts.detach().to(torch.float32).contiguous()
        q = x.detach().to(torch.float32).contiguous()
        face = torch.empty(len(q), dtype=torch.int32, device=x.device)
        bary = torch.empty((len(q), 3), dtype=torch.float32, device=x.device)
        sign = torch.empty(len(q), dtype=torch.float32, device=x.device)
        # On CUDA, Warp works on torch's current stream: ordered after the kernels that wrote the
        # inputs and before those that read the outputs, without a device-wide sync.
        scope = wp.ScopedStream(wp.stream_from_torch(x.device)) if x.device.type == "cuda" else contextlib.nullcontext()
        with scope:
            if entry is None:
                points = wp.array(v32.cpu().numpy(), dtype=wp.vec3, device=dev)
                idx = wp.array(self.faces.cpu().numpy().astype("int32").reshape(-1), dtype=wp.int32, device=dev)
                mesh = wp.Mesh(points=points, indices=idx)
                entry = self._meshes[dev] = (mesh, points, idx)
            else:
                mesh, points, _ = entry
                wp.copy(points, wp.from_torch(v32, dtype=wp.vec3))
                mesh.refit()
            wp.launch(kernels.closest_face_kernel, dim=len(q), device=dev,
                      inputs=[entry[0].id, wp.from_torch(q, dtype=wp.vec3), 1.0e6],
                      outputs=[wp.from_torch(face, dtype=wp.int32), wp.from_torch(bary, dtype=wp.vec3),
                               wp.from_torch(sign)])
        if bool((face < 0).any()):
            raise InputError("collision post-process: some garment points found no body triangle")
        return face.long(), bary.to(x.dtype), torch.where(sign < 0, -1.0, 1.0).to(x.dtype)


@torch.no_grad()
def push_out(points: torch.Tensor, body_vertices: torch.Tensor, surface: BodySurface, *,
             clearance: float = DEFAULT_CLEARANCE) -> tuple[torch.Tensor, torch.Tensor]:
    """The collision post-process: move vertices closer than ``clearance`` to the body out to it.

    points [m], shape (N, P, 3) (or (P, 3)); body_vertices [m] of the posed body, shape (N, V, 3)
    (or (V, 3)); surface: the body's :class:`BodySurface`. Each vertex with signed distance below
    ``clearance`` moves to c + clearance n (c its closest body point, n the outward direction, see
    the module doc). Returns (points [m] of the input's shape, moved (bool, (N, P))).
    """
    single = points.dim() == 2
    q = surface.query(points if not single else points[None], body_vertices)
    pts = points[None] if single else points
    moved = q.signed_distance < clearance
    out = torch.where(moved[..., None], q.closest + clearance * q.normal, pts)
    return (out[0], moved[0]) if single else (out, moved)
