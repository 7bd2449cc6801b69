"""The body-surface query in torch: the twin of :mod:`simgen.body.surface_query` (its specification:
closest face, exact closest point, signed distance, normal), differentiable; only the nearest-triangle
search (below) runs in Warp.

Implemented here: the pseudo-normal sign (the solver's; the winding-number variant and the body part
rule are Warp-only). d goes through the body's nearest TRIANGLE (the exact point-triangle closest
point, :func:`closest_point_triangle`, in the branch order of the Warp function): inside the
triangle, the plane distance along its unit normal (linear in x); on an edge or at a vertex,
d = s |x - c| with the sign s of the feature's angle-weighted pseudo-normal (the sum of the two face
normals of an edge; the angle-weighted sum of a vertex's face normals), s = +1 where
pseudo-normal . (x - c) > 0, else -1. The distance is differentiable in the cloth and body
positions; the nearest face, the closest point's region and the sign are not.

Used by the SNUG losses and the physics evaluation (:mod:`simgen.physics.contact`,
:mod:`simgen.physics.friction`) and by the torch backend of the learned models' collision
post-process (:mod:`simgen.learn.collision`). tests/test_body_surface_query.py holds it equal to
the Warp implementation in float64.

Nearest triangle search (no gradient): Warp's BVH, the solver's own query
(:func:`simgen.body.surface_query.nearest_face_kernel`), one warp.Mesh per frame of a call, built at
its first use and refit after, all frames in one launch, on the tensors' device (CPU or CUDA, on
torch's stream). Its float32 distances pick the triangle (of triangles equally near within float32,
either); the distance itself is computed here in the caller's precision. Unlike the solver's
query, it has no query distance: every point finds its triangle. (A search in torch, over
spatial clusters of triangles, took 99% of a SNUG training step on the GPU and 18x the BVH's time
on the CPU; BENCHMARKS.md.)
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from simgen.errors import InputError

__all__ = ["BodySurface", "BodyDistance", "body_distance", "closest_point_triangle", "REGION_INTERIOR"]


# Regions of a triangle's closest point (Ericson's Voronoi regions): vertices a, b, c; edges ab, ac,
# bc; the face interior.
REGION_A, REGION_B, REGION_C, REGION_AB, REGION_AC, REGION_BC, REGION_INTERIOR = range(7)


def _dot(u: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    return (u * v).sum(-1)


def _safe(den: torch.Tensor) -> torch.Tensor:
    return torch.where(den == 0, torch.ones_like(den), den)


def _regions(d1, d2, aa, ab_ac, cc):
    """Closest-point region and weights (v, w) of corners b, c (a gets 1 - v - w) from the two dot
    products d1 = ab.ap, d2 = ac.ap and the triangle's aa = ab.ab, ab_ac = ab.ac, cc = ac.ac, with the
    branch order of the solver's Warp function (Ericson's Voronoi regions)."""
    d3, d4 = d1 - aa, d2 - ab_ac          # ab.bp, ac.bp
    d5, d6 = d1 - ab_ac, d2 - cc          # ab.cp, ac.cp
    vc = d1 * d4 - d3 * d2
    vb = d5 * d2 - d1 * d6
    va = d3 * d6 - d5 * d4
    zero, one = torch.zeros_like(d1), torch.ones_like(d1)
    t_ab = d1 / _safe(d1 - d3)
    t_ac = d2 / _safe(d2 - d6)
    t_bc = (d4 - d3) / _safe((d4 - d3) + (d5 - d6))
    denom = 1.0 / _safe(va + vb + vc)
    branches = [
        (REGION_A, (d1 <= 0) & (d2 <= 0), zero, zero),
        (REGION_B, (d3 >= 0) & (d4 <= d3), one, zero),
        (REGION_AB, (vc <= 0) & (d1 >= 0) & (d3 <= 0), t_ab, zero),
        (REGION_C, (d6 >= 0) & (d5 <= d6), zero, one),
        (REGION_AC, (vb <= 0) & (d2 >= 0) & (d6 <= 0), zero, t_ac),
        (REGION_BC, (va <= 0) & (d4 - d3 >= 0) & (d5 - d6 >= 0), 1 - t_bc, t_bc),
    ]
    region = torch.full(d1.shape, REGION_INTERIOR, dtype=torch.long, device=d1.device)
    v, w = vb * denom, vc * denom
    for code, cond, bv, bw in reversed(branches):  # the first true condition wins, as in sequential ifs
        region = torch.where(cond, code, region)
        v = torch.where(cond, bv, v)
        w = torch.where(cond, bw, w)
    return region, v, w


def closest_point_triangle(p, a, b, c) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Exact closest point of triangles (a, b, c) to points p, all (..., 3) broadcastable.

    Returns (closest (..., 3), barycentric weights of a, b, c (..., 3), region (...) long: one of
    REGION_A..REGION_INTERIOR), with the same branch order as the solver's Warp function.
    """
    ab, ac, ap = b - a, c - a, p - a
    region, v, w = _regions(_dot(ab, ap), _dot(ac, ap), _dot(ab, ab), _dot(ab, ac), _dot(ac, ac))
    closest = a + v[..., None] * ab + w[..., None] * ac
    return closest, torch.stack([1 - v - w, v, w], dim=-1), region


class BodySurface:
    """Topology of a closed, outward-oriented body mesh for signed distances (one per body model).

    faces (Fb, 3) int, counter-clockwise seen from outside; reference_vertices [m] (Vb, 3): any
    pose of the body (the rest pose; it fixes Vb). Tensors live on ``device`` (move with :meth:`to`).
    """

    def __init__(self, faces, reference_vertices, *, device=None) -> None:
        self._bvh = None
        f = np.asarray(faces)
        v = np.asarray(reference_vertices, dtype=np.float64)
        if f.ndim != 2 or f.shape[1] != 3 or len(f) == 0 or not np.issubdtype(f.dtype, np.integer):
            raise InputError(f"body faces must be integers of shape (F, 3), got {f.dtype} {f.shape}")
        if v.ndim != 2 or v.shape[1] != 3:
            raise InputError(f"body reference vertices must have shape (Vb, 3), got {v.shape}")
        if f.min() < 0 or f.max() >= len(v):
            raise InputError(f"body faces index vertex {int(f.max())} of {len(v)}")
        f = f.astype(np.int64)
        self.num_vertices = int(len(v))
        # Undirected edges; edge k of face t joins f[t, k] and f[t, (k + 1) % 3].
        a = f.reshape(-1)
        b = f[:, [1, 2, 0]].reshape(-1)
        key = np.minimum(a, b) * len(v) + np.maximum(a, b)
        uniq, inverse = np.unique(key, return_inverse=True)
        face_edges = inverse.reshape(-1, 3)
        edge_faces = np.full((len(uniq), 2), -1, dtype=np.int64)
        face_of = np.repeat(np.arange(len(f)), 3)
        order = np.argsort(inverse, kind="stable")
        first = np.r_[True, inverse[order][1:] != inverse[order][:-1]]
        edge_faces[inverse[order][first], 0] = face_of[order][first]
        rest = ~first
        edge_faces[inverse[order][rest], 1] = face_of[order][rest]
        # An edge with one face (an open mesh) uses that face's normal alone.
        edge_faces[:, 1] = np.where(edge_faces[:, 1] < 0, edge_faces[:, 0], edge_faces[:, 1])
        self.faces = torch.as_tensor(f)
        self.face_edges = torch.as_tensor(face_edges.astype(np.int64))
        self.edge_faces = torch.as_tensor(edge_faces)
        if device is not None:
            self.to(device)

    @classmethod
    def from_body(cls, body, **kw) -> "BodySurface":
        """The surface of a :class:`simgen.body.BodyModel` (its template vertices as the reference)."""
        return cls(body.faces, body.v_template, **kw)

    @property
    def num_faces(self) -> int:
        return int(self.faces.shape[0])

    @property
    def device(self) -> torch.device:
        return self.faces.device

    def to(self, device) -> "BodySurface":
        """Move the topology tensors to ``device`` (in place; returns self)."""
        for name in ("faces", "face_edges", "edge_faces"):
            setattr(self, name, getattr(self, name).to(device))
        self._bvh = None
        return self

    # -- per-frame geometry ---------------------------------------------------------------------

    def frame_geometry(self, vertices: torch.Tensor) -> dict:
        """Per-frame data of posed bodies, vertices [m] (Vb, 3) or (B, Vb, 3) for B frames: triangle
        corners (..., Fb, 3, 3), unit face normals (..., Fb, 3), vertex and edge pseudo-normals, and the
        vertices themselves; every entry keeps the input's leading frame dimension (if any)."""
        if vertices.ndim == 2:
            return {k: v[0] for k, v in self.frame_geometry(vertices[None]).items()}
        nb = vertices.shape[0]
        tri = vertices[:, self.faces]                                          # (B, Fb, 3, 3)
        n = torch.cross(tri[..., 1, :] - tri[..., 0, :], tri[..., 2, :] - tri[..., 0, :], dim=-1)
        fn = n / n.norm(dim=-1, keepdim=True).clamp_min(1e-30)
        # Interior angle at each corner: weights of the vertex pseudo-normals.
        angles = []
        for k in range(3):
            u = tri[..., (k + 1) % 3, :] - tri[..., k, :]
            w = tri[..., (k + 2) % 3, :] - tri[..., k, :]
            cos = _dot(u, w) / (u.norm(dim=-1) * w.norm(dim=-1)).clamp_min(1e-30)
            angles.append(torch.acos(cos.clamp(-1.0, 1.0)))
        angles = torch.stack(angles, dim=-1)                                    # (B, Fb, 3)
        vn = torch.zeros((nb, self.num_vertices, 3), dtype=vertices.dtype, device=vertices.device)
        vn.index_add_(1, self.faces.reshape(-1), (angles[..., None] * fn[..., None, :]).reshape(nb, -1, 3))
        en = fn[:, self.edge_faces[:, 0]] + fn[:, self.edge_faces[:, 1]]
        return dict(vertices=vertices, tri=tri, face_normal=fn, vertex_normal=vn, edge_normal=en)

    # -- search ---------------------------------------------------------------------------------

    @torch.no_grad()
    def nearest_faces(self, points: torch.Tensor, geometry: dict) -> torch.Tensor:
        """Index of the nearest body triangle of each point [m] (module doc: Warp's BVH): (P, 3) with
        one frame's geometry -> (P,) long, or (B, P, 3) with B frames' geometry (:meth:`frame_geometry`)
        -> (B, P)."""
        if points.ndim == 2:
            return self.nearest_faces(points[None], {k_: v[None] for k_, v in geometry.items()})[0]
        if self._bvh is None:
            self._bvh = _BvhSearch(self.faces)
        return self._bvh.nearest(points, geometry["vertices"])

    @torch.no_grad()
    def nearest_faces_brute_force(self, points: torch.Tensor, vertices: torch.Tensor, *,
                                  chunk: int = 64) -> torch.Tensor:
        """Reference search over every triangle (tests): nearest triangle of each point (P, 3) -> (P,)."""
        tri = vertices[self.faces]
        out = torch.empty(points.shape[0], dtype=torch.long, device=points.device)
        for start in range(0, points.shape[0], chunk):
            q = points[start:start + chunk][:, None, :]
            c, _, _ = closest_point_triangle(q, tri[None, :, 0], tri[None, :, 1], tri[None, :, 2])
            out[start:start + chunk] = ((q - c) ** 2).sum(-1).argmin(dim=1)
        return out


class _BvhSearch:
    """The nearest-triangle search (module doc): one warp.Mesh per frame slot of a call, on the
    faces' device, built on its first frame and refit to each later one (a refit tree stays exact,
    only its pruning gets looser as poses drift from the first)."""

    def __init__(self, faces: torch.Tensor) -> None:
        import warp as wp

        from simgen._warp_log import init_warp

        self.device = faces.device
        init_warp(str(self.device))
        self.wp_device = wp.device_from_torch(self.device)
        self._indices_t = faces.to(torch.int32).reshape(-1).contiguous()
        self.indices = wp.from_torch(self._indices_t, dtype=wp.int32)
        self.slots: list = []           # (float32 points (Vb, 3) torch buffer, warp.Mesh)
        self.ids = None                 # (slots,) uint64 mesh ids on the device

    def nearest(self, points: torch.Tensor, vertices: torch.Tensor) -> torch.Tensor:
        """Nearest triangle of points [m] (B, P, 3) on the bodies vertices [m] (B, Vb, 3): (B, P) long."""
        import contextlib

        import warp as wp

        from simgen.body.surface_query import nearest_face_kernel

        nb, npts = points.shape[:2]
        cuda = self.device.type == "cuda"
        stream = wp.ScopedStream(wp.stream_from_torch(self.device)) if cuda else contextlib.nullcontext()
        with wp.ScopedDevice(self.wp_device), stream:
            for b in range(nb):
                v = vertices[b].detach().to(torch.float32)
                if b < len(self.slots):
                    buf, mesh = self.slots[b]
                    buf.copy_(v)
                    mesh.refit()
                else:
                    buf = v.contiguous().clone()
                    mesh = wp.Mesh(points=wp.from_torch(buf, dtype=wp.vec3), indices=self.indices)
                    self.slots.append((buf, mesh))
                    self.ids = None
            if self.ids is None:
                self.ids = wp.array(np.array([m.id for _, m in self.slots], dtype=np.uint64), dtype=wp.uint64)
            q = points.detach().to(torch.float32).reshape(-1, 3).contiguous()
            face = torch.empty(nb * npts, dtype=torch.int32, device=self.device)
            wp.launch(nearest_face_kernel, dim=nb * npts,
                      inputs=[self.ids, wp.from_torch(q, dtype=wp.vec3), npts, wp.from_torch(face, dtype=wp.int32)])
        return face.reshape(nb, npts).long()


@dataclass
class BodyDistance:
    """Signed distances of cloth vertices to a posed body (see the module doc).

    distance [m] (..., V): signed, < 0 inside, differentiable in the cloth (and body) positions;
    normal (..., V, 3): outward unit normal = grad(d) (detached; the closest point is
    x - distance * normal); face (..., V) long: nearest body triangle; bary (..., V, 3): barycentric
    weights of its corners at the closest point (detached).
    """

    distance: torch.Tensor
    normal: torch.Tensor
    face: torch.Tensor
    bary: torch.Tensor


def _signed_on_faces(x, geometry, surface: BodySurface, face, frame):
    """Differentiable signed distance of points x (P, 3) through the given triangles (P,) of the
    frames ``frame`` (P,) long of ``geometry`` (B frames, :meth:`BodySurface.frame_geometry`)."""
    nf, nv, ne = surface.num_faces, surface.num_vertices, surface.edge_faces.shape[0]
    gf = face + frame * nf
    tri = geometry["tri"].reshape(-1, 3, 3)[gf]
    a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]
    with torch.no_grad():
        _, bary, region = closest_point_triangle(x.detach(), a.detach(), b.detach(), c.detach())
    fn = geometry["face_normal"].reshape(-1, 3)[gf]
    # The closest point again, differentiably, within its (fixed) region.
    ab, ac, bc = b - a, c - a, c - b
    t_ab = (_dot(x - a, ab) / _dot(ab, ab)).clamp(0.0, 1.0)[:, None]
    t_ac = (_dot(x - a, ac) / _dot(ac, ac)).clamp(0.0, 1.0)[:, None]
    t_bc = (_dot(x - b, bc) / _dot(bc, bc)).clamp(0.0, 1.0)[:, None]
    candidates = [a, b, c, a + t_ab * ab, a + t_ac * ac, b + t_bc * bc]
    closest = x.detach().clone()
    for code, cand in enumerate(candidates):
        closest = torch.where((region == code)[:, None], cand, closest)
    # Pseudo-normal of the closest feature (vertex or edge) for the sign.
    with torch.no_grad():
        fv = surface.faces[face] + (frame * nv)[:, None]
        fe = surface.face_edges[face] + (frame * ne)[:, None]
        vn, en = geometry["vertex_normal"].reshape(-1, 3), geometry["edge_normal"].reshape(-1, 3)
        # Face edge 0 = (a, b), 1 = (b, c), 2 = (c, a).
        feature_normal = torch.zeros_like(x)
        for code, pn in ((REGION_A, vn[fv[:, 0]]), (REGION_B, vn[fv[:, 1]]), (REGION_C, vn[fv[:, 2]]),
                         (REGION_AB, en[fe[:, 0]]), (REGION_BC, en[fe[:, 1]]), (REGION_AC, en[fe[:, 2]])):
            feature_normal = torch.where((region == code)[:, None], pn, feature_normal)
        sign = torch.where(_dot(feature_normal, x.detach() - closest.detach()) > 0, 1.0, -1.0).to(x.dtype)
    diff = x - closest
    dist2 = _dot(diff, diff)
    tiny = 1e-12
    ok = dist2 > tiny * tiny
    dist = torch.where(ok, dist2, torch.ones_like(dist2)).sqrt()
    point_d = torch.where(ok, sign * dist, torch.zeros_like(dist))
    plane_d = _dot(x - a, fn)
    interior = region == REGION_INTERIOR
    d = torch.where(interior, plane_d, point_d)
    with torch.no_grad():
        point_n = torch.where(ok[:, None], sign[:, None] * diff.detach() / dist.detach()[:, None], fn.detach())
        normal = torch.where(interior[:, None], fn.detach(), point_n)
    return d, normal, bary


def body_distance(x: torch.Tensor, body_vertices: torch.Tensor, surface: BodySurface, *,
                  frames_at_once: int = 64) -> BodyDistance:
    """Signed distance of every cloth vertex to the posed body (module doc), batched over frames.

    x [m] (..., V, 3); body_vertices [m] (..., Vb, 3) with leading dims broadcastable to x's (one
    body per frame, or one for all); surface: the body's :class:`BodySurface` (on x's device).
    frames_at_once: frames whose body geometry is held and searched together (memory ~ 2 MB per
    frame of the 13k-vertex body in float32).
    """
    if body_vertices.shape[-2:] != (surface.num_vertices, 3):
        raise InputError(f"body vertices must have shape (..., {surface.num_vertices}, 3), got "
                         f"{tuple(body_vertices.shape)}")
    if x.ndim < 2 or x.shape[-1] != 3:
        raise InputError(f"cloth positions must have shape (..., V, 3), got {tuple(x.shape)}")
    lead = torch.broadcast_shapes(x.shape[:-2], body_vertices.shape[:-2])
    nv = x.shape[-2]
    xs = x.expand(lead + x.shape[-2:]).reshape((-1, nv, 3))
    bs = body_vertices.to(dtype=x.dtype).expand(lead + body_vertices.shape[-2:]).reshape((-1, surface.num_vertices, 3))
    static = math.prod(body_vertices.shape[:-2]) == 1      # one body for every frame: its geometry once
    ds, ns, fs, bys = [], [], [], []
    geometry = surface.frame_geometry(bs[:1]) if static else None
    for f0 in range(0, xs.shape[0], frames_at_once):
        f1 = min(xs.shape[0], f0 + frames_at_once)
        if not static:
            geometry = surface.frame_geometry(bs[f0:f1])
        detached = {k_: v.detach() for k_, v in geometry.items()}
        pts = xs[f0:f1]
        if static:
            face = surface.nearest_faces(pts.detach().reshape(1, -1, 3), detached).reshape(f1 - f0, nv)
            frame = torch.zeros(face.numel(), dtype=torch.long, device=x.device)
        else:
            face = surface.nearest_faces(pts.detach(), detached)
            frame = torch.arange(f1 - f0, device=x.device).repeat_interleave(nv)
        d, n, bary = _signed_on_faces(pts.reshape(-1, 3), geometry, surface, face.reshape(-1), frame)
        ds.append(d.reshape(f1 - f0, nv))
        ns.append(n.reshape(f1 - f0, nv, 3))
        fs.append(face)
        bys.append(bary.reshape(f1 - f0, nv, 3))
    shape = lead + (nv,)
    return BodyDistance(distance=torch.cat(ds).reshape(shape), normal=torch.cat(ns).reshape(shape + (3,)),
                        face=torch.cat(fs).reshape(shape), bary=torch.cat(bys).reshape(shape + (3,)))
