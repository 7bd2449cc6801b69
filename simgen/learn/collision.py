"""Collision post-process of predicted garments (thesis ch. 4, Fig. 4.3), in torch.

After skinning, garment vertices that ended inside the body (or closer to it than a clearance) are
pushed out of their closest body primitive until they are ``clearance`` [m] outside. The thesis
gives no distance; 2 mm is the value in the authors' released code, which moves a vertex along the
normal of its nearest body *vertex*. Here the closest point c is on the nearest *triangle*: a
vertex x with signed distance d < clearance moves to x + (clearance - d) n = c + clearance n, n the
outward unit normal of the distance field at x (the face normal wherever c is inside a triangle,
the exact direction away from an edge or a corner elsewhere); the vertex ends exactly
``clearance`` from that primitive.

The closest point, d and n are the body-surface query of :mod:`simgen.body.surface_query` with the
pseudo-normal sign (the solver's), by one of two implementations (``CollisionSurface(backend=...)``):

- ``"warp"`` (the default when warp-lang imports): the Warp implementation (BVH on a ``wp.Mesh``
  built once and refit for every frame, the distance exact in the tensors' dtype), on the tensors'
  device (CPU or CUDA, on torch's stream, memory shared through ``wp.from_torch``);
- ``"torch"``: the torch implementation (:func:`simgen.physics.surface_query.body_distance`: the
  nearest triangle from Warp's BVH, the distance differentiable in torch), all frames at once.

tests/test_body_surface_query.py holds the two implementations equal; tests/test_learn_collision.py
holds the post-process against the winding-number query of :func:`simgen.body.surface.project_to_surface`.

Moving single vertices stretches the triangles around them: a vertex pushed 5 mm out of a 1 cm
edge ring stretches its edges ~12% (the learned model's post-process raised the simulation's
strain energy 14-fold, BENCHMARKS.md). With a :class:`MeshSpread` of the garment, the push is
spread over the surrounding cloth instead: the displacement field is smoothed over the mesh's
vertex rings a few times, each time raised back to at least the push every colliding vertex needs
along its normal, so the colliding vertices end where the per-vertex push puts them (or farther
out) and their neighbours follow part of the way, as cloth lifted at a point does.
"""

from __future__ import annotations

import contextlib

import numpy as np
import torch

from simgen.errors import InputError
from simgen.physics.surface_query import BodyDistance, BodySurface, body_distance

__all__ = ["DEFAULT_CLEARANCE", "BACKENDS", "CollisionSurface", "MeshSpread", "push_out"]

BACKENDS = ("auto", "warp", "torch")

#: Distance [m] outside the body at which the post-process leaves colliding vertices (authors' code).
DEFAULT_CLEARANCE = 0.002


class CollisionSurface:
    """The body surface as the collision post-process queries it, prepared once.

    faces, shape (F, 3) (outward counter-clockwise winding, as every simgen body); reference_vertices
    [m], shape (V, 3): any pose of the body (the template); backend: "warp", "torch" or "auto"
    (warp when it imports).
    """

    def __init__(self, faces, reference_vertices, *, backend: str = "auto", device=None):
        if backend not in BACKENDS:
            raise InputError(f"collision backend {backend!r} is not one of {', '.join(BACKENDS)}")
        if backend == "auto":
            import importlib.util

            backend = "warp" if importlib.util.find_spec("warp") is not None else "torch"
        self.backend = backend
        self.surface = BodySurface(faces, reference_vertices, device=device)
        self._meshes: dict = {}

    @property
    def num_vertices(self) -> int:
        return self.surface.num_vertices

    def to(self, device) -> "CollisionSurface":
        """Move the topology tensors to ``device`` (in place; returns self)."""
        self.surface.to(device)
        return self

    @torch.no_grad()
    def query(self, points: torch.Tensor, vertices: torch.Tensor) -> BodyDistance:
        """Closest body points of garment points.

        points [m], shape (N, P, 3); vertices [m] of the posed body, shape (N, V, 3) (or (P, 3) and
        (V, 3) for a single frame). Returns :class:`~simgen.physics.surface_query.BodyDistance` of
        shape (N, P) (detached).
        """
        if points.dim() == 2:
            points = points[None]
        if vertices.dim() == 2:
            vertices = vertices[None]
        if vertices.shape[1:] != (self.num_vertices, 3) or vertices.shape[0] != points.shape[0]:
            raise InputError(f"body vertices must have shape ({points.shape[0]}, {self.num_vertices}, 3), "
                             f"got {tuple(vertices.shape)}")
        vertices = vertices.to(points.dtype)
        if self.backend == "torch":
            return body_distance(points, vertices, self.surface)
        frames = [self._warp_query(points[i], vertices[i]) for i in range(points.shape[0])]
        distance, normal, face, bary = (torch.stack(t) for t in zip(*frames))
        if bool((face < 0).any()):    # one host synchronisation per call, not per frame
            raise InputError("collision post-process: some garment points found no body triangle")
        return BodyDistance(distance, normal, face, bary)

    def _warp_query(self, x: torch.Tensor, verts: torch.Tensor):
        """(distance (P,), normal (P, 3), face (P,) int64 (-1: none found), bary (P, 3)) of points
        x [m] (P, 3) on the body with vertices verts [m] (V, 3), both float32 or float64; launched on
        torch's current stream without waiting for it."""
        import warp as wp

        from simgen._warp_log import init_warp
        from simgen.body.surface_query import query_kernel

        dev = "cpu" if x.device.type == "cpu" else f"cuda:{x.device.index or 0}"
        init_warp(dev)
        scalar, vec3 = (wp.float64, wp.vec3d) if x.dtype == torch.float64 else (wp.float32, wp.vec3)
        x, verts = x.detach().contiguous(), verts.detach().contiguous()
        n = len(x)
        distance, normal, closest, bary = (torch.empty(s, dtype=x.dtype, device=x.device)
                                           for s in ((n,), (n, 3), (n, 3), (n, 3)))
        face = torch.empty(n, dtype=torch.int32, device=x.device)
        # On CUDA, Warp works on torch's current stream: ordered after the kernels that wrote the
        # inputs and before those that read the outputs, without a device-wide sync.
        scope = wp.ScopedStream(wp.stream_from_torch(x.device)) if x.device.type == "cuda" else contextlib.nullcontext()
        with scope:
            entry = self._meshes.get(dev)
            v32 = verts.to(torch.float32)
            if entry is None:
                faces = self.surface.faces.cpu().numpy().astype(np.int32)
                points = wp.array(v32.cpu().numpy(), dtype=wp.vec3, device=dev)
                indices = wp.array(faces.reshape(-1), dtype=wp.int32, device=dev)
                entry = self._meshes[dev] = (wp.Mesh(points=points, indices=indices), points,
                                             wp.array(faces, dtype=wp.int32, device=dev))
            else:
                wp.copy(entry[1], wp.from_torch(v32, dtype=wp.vec3))
                entry[0].refit()
            wp.launch(query_kernel(scalar), dim=n, device=dev,
                      inputs=[entry[0].id, wp.from_torch(verts, dtype=vec3), entry[2], wp.from_torch(x, dtype=vec3),
                              1.0e6, 0],
                      outputs=[wp.from_torch(distance), wp.from_torch(normal, dtype=vec3),
                               wp.from_torch(closest, dtype=vec3), wp.from_torch(face),
                               wp.from_torch(bary, dtype=vec3)])
        return distance, normal, face.long(), bary


class MeshSpread:
    """Spreads a per-vertex displacement over a garment mesh's vertex rings (module doc).

    faces (F, 3) of the garment; num_vertices P; rings: smoothing passes (each reaches one ring
    farther). Applied to displacements (N, P, 3) on the faces' device.
    """

    #: Smoothing passes of the default: the push reaches about this many edge rings around a vertex.
    RINGS = 8

    def __init__(self, faces, num_vertices: int, rings: int = RINGS) -> None:
        f = torch.as_tensor(np.asarray(faces) if not torch.is_tensor(faces) else faces, dtype=torch.int64)
        edges = torch.cat([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
        edges = torch.unique(torch.sort(edges, dim=1).values, dim=0)             # each undirected edge once
        both = torch.cat([edges, edges.flip(1)])
        degree = torch.bincount(both[:, 0], minlength=num_vertices).clamp(min=1).to(torch.float32)
        self.rows, self.cols, self.weight = both[:, 0], both[:, 1], 1.0 / degree[both[:, 0]]
        self.rings = int(rings)

    def to(self, device) -> MeshSpread:
        self.rows, self.cols, self.weight = (t.to(device) for t in (self.rows, self.cols, self.weight))
        return self

    def neighbour_mean(self, d: torch.Tensor) -> torch.Tensor:
        """The mean over each vertex's neighbours of d (N, P, 3)."""
        out = torch.zeros_like(d)
        out.index_add_(1, self.rows, d[:, self.cols] * self.weight.to(d.dtype)[None, :, None])
        return out


@torch.no_grad()
def push_out(points: torch.Tensor, body_vertices: torch.Tensor, surface: CollisionSurface, *,
             clearance: float = DEFAULT_CLEARANCE,
             spread: MeshSpread | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """The collision post-process: move vertices closer than ``clearance`` to the body out to it.

    points [m], shape (N, P, 3) (or (P, 3)); body_vertices [m] of the posed body, shape (N, V, 3)
    (or (V, 3)); surface: the body's :class:`CollisionSurface`. Each vertex with signed distance d
    below ``clearance`` moves to x + (clearance - d) n (see the module doc); with ``spread`` (the
    garment's :class:`MeshSpread`), that push is spread over the cloth around it, and the vertices
    it brought closer than ``clearance`` (few: they move outward too) get the per-vertex push.
    Returns (points [m] of the input's shape, moved (bool, (N, P)): the vertices that collided).
    """
    single = points.dim() == 2
    pts = points[None] if single else points
    q = surface.query(pts, body_vertices)
    moved = q.distance < clearance
    need = (clearance - q.distance).clamp(min=0.0)
    push = need[..., None] * q.normal
    if spread is not None and bool(moved.any()):
        for _ in range(spread.rings):
            push = 0.5 * (push + spread.neighbour_mean(push))
            short = (need - (push * q.normal).sum(-1)).clamp(min=0.0)      # colliding vertices keep their push
            push = push + short[..., None] * q.normal
        out, _ = push_out(pts + push, body_vertices, surface, clearance=clearance)
    else:
        out = torch.where(moved[..., None], pts + push, pts)
    return (out[0], moved[0]) if single else (out, moved)
