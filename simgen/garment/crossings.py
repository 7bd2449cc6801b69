"""Cloth passing through itself: the crossing-edge counter.

Definition. An edge (p, q) of a garment's triangle mesh *crosses* a triangle (a, b, c) of the same
mesh when the two share no vertex and the open segment meets the triangle's interior, decided
exactly in float64 with no tolerance by five orientation signs, orient(u, v, w, z) = (v - u) .
((w - u) x (z - u)):

    orient(a, b, c, p) and orient(a, b, c, q) have opposite signs (p and q on either side of the
    triangle's plane), and orient(p, q, a, b), orient(p, q, b, c), orient(p, q, c, a) are all
    positive or all negative (the segment's line passes inside the triangle).

A zero anywhere (the segment touching the plane, an edge or a vertex of the triangle) is no
crossing: touching is contact, not passing through. An edge that crosses any triangle is a
*crossing edge*; the count of a frame is the number of crossing edges. A clean fold (two layers
lying on each other, however close) counts 0; a sheet pushed through another counts the edges
that pierce it, and so does each of the other sheet's edges that pierce the first.

Candidates come from a BVH over the triangles of each copy (float32 boxes padded by
:data:`BOX_PAD`, so no pair that could cross is missed), the test itself runs in float64 in a Warp
kernel (CPU or CUDA).
Used by ``simgen dataset check`` and ``simgen eval physics``.
"""

from __future__ import annotations

import numpy as np
import warp as wp

from simgen.body.surface_query import MeshIdSubset
from simgen.errors import InputError
from simgen.garment.mesh import unique_edges

__all__ = ["BOX_PAD", "CrossingCounter", "count_crossing_edges", "crossing_edges", "edge_query",
           "segment_crosses_triangle"]

#: [m] padding of the float32 candidate boxes (float32 rounds a coordinate of a few metres by < 1e-6 m).
BOX_PAD = 1.0e-5


@wp.func
def _orient(u: wp.vec3d, v: wp.vec3d, w: wp.vec3d, z: wp.vec3d) -> wp.float64:
    return wp.dot(v - u, wp.cross(w - u, z - u))


@wp.func
def segment_crosses_triangle(p: wp.vec3d, q: wp.vec3d, a: wp.vec3d, b: wp.vec3d, c: wp.vec3d) -> int:
    zero = wp.float64(0.0)
    sp = _orient(a, b, c, p)
    sq = _orient(a, b, c, q)
    if not ((sp > zero and sq < zero) or (sp < zero and sq > zero)):
        return 0
    t1 = _orient(p, q, a, b)
    t2 = _orient(p, q, b, c)
    t3 = _orient(p, q, c, a)
    if (t1 > zero and t2 > zero and t3 > zero) or (t1 < zero and t2 < zero and t3 < zero):
        return 1
    return 0


@wp.func
def edge_query(mesh: wp.uint64, p: wp.vec3d, q: wp.vec3d, pad: float):
    """A BVH query for the triangles whose float32 boxes meet the edge (p, q)'s box grown by pad [m]."""
    pf = wp.vec3(wp.float32(p[0]), wp.float32(p[1]), wp.float32(p[2]))
    qf = wp.vec3(wp.float32(q[0]), wp.float32(q[1]), wp.float32(q[2]))
    return wp.mesh_query_aabb(mesh, wp.min(pf, qf) - wp.vec3(pad), wp.max(pf, qf) + wp.vec3(pad))


@wp.kernel(enable_backward=False)
def _to_float64(points: wp.array(dtype=wp.vec3), x: wp.array(dtype=wp.vec3d)):
    i = wp.tid()
    p = points[i]
    x[i] = wp.vec3d(wp.float64(p[0]), wp.float64(p[1]), wp.float64(p[2]))


@wp.kernel(enable_backward=False)
def _crossing_kernel(meshes: wp.array(dtype=wp.uint64), x: wp.array(dtype=wp.vec3d),
                     faces: wp.array(dtype=wp.int32, ndim=2), edges: wp.array(dtype=wp.int32, ndim=2), pad: float,
                     num_vertices: int, crossing: wp.array(dtype=wp.int32), per_instance: wp.array(dtype=wp.int32)):
    # Thread = (instance k, edge e of one copy); copy k owns vertices [k V, (k + 1) V) and its own BVH
    # (copies overlap in space: one BVH over all would hand every edge the other copies' triangles);
    # a copy whose BVH id is 0 is not counted.
    tid = wp.tid()
    num_edges = edges.shape[0]
    instance = tid / num_edges
    e = tid - instance * num_edges
    crossing[tid] = 0
    if meshes[instance] == wp.uint64(0):
        return
    base = instance * num_vertices
    i = edges[e, 0] + base
    j = edges[e, 1] + base
    p = x[i]
    q = x[j]
    query = edge_query(meshes[instance], p, q, pad)
    f = int(0)
    while wp.mesh_query_aabb_next(query, f):
        a = faces[f, 0] + base
        b = faces[f, 1] + base
        c = faces[f, 2] + base
        if a == i or a == j or b == i or b == j or c == i or c == j:
            continue
        if segment_crosses_triangle(p, q, x[a], x[b], x[c]) != 0:
            crossing[tid] = 1
            wp.atomic_add(per_instance, instance, 1)
            return


@wp.kernel(enable_backward=False)
def _pairs_kernel(mesh: wp.uint64, x: wp.array(dtype=wp.vec3d), faces: wp.array(dtype=wp.int32, ndim=2),
                  edges: wp.array(dtype=wp.int32, ndim=2), pad: float, count: wp.array(dtype=wp.int32),
                  pairs: wp.array(dtype=wp.int32, ndim=2)):
    # Thread = edge e of one copy; every triangle it crosses is appended as (e, f) while room lasts
    # (count keeps counting past the capacity, so the caller can grow the buffer and rerun).
    e = wp.tid()
    i = edges[e, 0]
    j = edges[e, 1]
    p = x[i]
    q = x[j]
    query = edge_query(mesh, p, q, pad)
    f = int(0)
    while wp.mesh_query_aabb_next(query, f):
        a = faces[f, 0]
        b = faces[f, 1]
        c = faces[f, 2]
        if a == i or a == j or b == i or b == j or c == i or c == j:
            continue
        if segment_crosses_triangle(p, q, x[a], x[b], x[c]) != 0:
            slot = wp.atomic_add(count, 0, 1)
            if slot < pairs.shape[0]:
                pairs[slot, 0] = e
                pairs[slot, 1] = f


class CrossingCounter:
    """Counts the crossing edges (module doc) of a triangle mesh over many frames, for one or for
    ``instances`` copies of it side by side (vertices instance by instance, as a batched
    simulation holds them; each copy is tested against itself only).

    faces (F, 3) int: the garment's triangles; num_vertices V of one copy; device: Warp device
    ("cpu", "cuda:0", ...). The BVHs are built on the first frame counted and refit for every later
    one, those of the copies loaded (:meth:`load`, :meth:`count_points`; on CUDA, when more than an
    eighth are, all of them: :meth:`MeshIdSubset.refit`).
    """

    def __init__(self, faces, num_vertices: int, device: str = "cpu", instances: int = 1) -> None:
        f = np.asarray(faces)
        if f.ndim != 2 or f.shape[1] != 3 or len(f) == 0 or f.min() < 0 or f.max() >= num_vertices:
            raise InputError(f"faces must have shape (F, 3) with indices below {num_vertices}")
        self.device = device
        self.num_vertices, self.instances = int(num_vertices), int(instances)
        self.edges = unique_edges(f).astype(np.int32)                                   # (E, 2) of one copy
        n = self.instances * self.num_vertices
        self._faces = wp.array(f.astype(np.int32), dtype=wp.int32, device=device)
        self._edges = wp.array(self.edges, dtype=wp.int32, device=device)
        self._x = wp.zeros(n, dtype=wp.vec3d, device=device)
        self._points = wp.zeros(n, dtype=wp.vec3, device=device)
        self._meshes: list = []      # built on the first frame's positions (module doc), then refit
        self._mesh_ids = None
        self._out = wp.zeros(self.instances * len(self.edges), dtype=wp.int32, device=device)
        self._per_instance = wp.zeros(self.instances, dtype=wp.int32, device=device)
        self._counted = None     # MeshIdSubset: mesh_ids with 0 for the copies a count leaves out

    def load(self, points: wp.array, instances=None) -> None:
        """Take positions [m] already on the device, float32 (instances * V,) vec3: their float64
        copy (:attr:`x64`) and the BVHs (:attr:`mesh_ids`) of the copies ``instances`` (None: all),
        built (all, the first time) or refit."""
        wp.copy(self._points, points)
        wp.launch(_to_float64, dim=len(self._x), device=self.device, inputs=[self._points], outputs=[self._x])
        self._refit(range(self.instances) if instances is None else instances)

    @property
    def x64(self) -> wp.array:
        """The positions last loaded, float64 (instances * V,) vec3d [m]."""
        return self._x

    @property
    def mesh_ids(self) -> wp.array:
        """One BVH (wp.Mesh id) per copy, (instances,) uint64, over the positions that copy was last
        loaded with (the last :meth:`load` of every copy: all of them)."""
        return self._mesh_ids

    @property
    def device_faces(self) -> wp.array:
        """One copy's triangles on the device, (F, 3) int32."""
        return self._faces

    @property
    def device_edges(self) -> wp.array:
        """One copy's edges (:attr:`edges`) on the device, (E, 2) int32."""
        return self._edges

    def _refit(self, instances) -> None:
        if not self._meshes:
            # A BVH is built on the first frame's positions: one built on placeholder points and
            # only refit would keep a tree that groups unrelated triangles (every query then walks it all).
            V, indices = self.num_vertices, self._faces.flatten()
            self._meshes = [wp.Mesh(points=self._points[k * V:(k + 1) * V], indices=indices)
                            for k in range(self.instances)]
            self._mesh_ids = wp.array([m.id for m in self._meshes], dtype=wp.uint64, device=self.device)
            self._counted = MeshIdSubset(self._meshes, self.device)
        self._counted.refit(instances)

    def _launch(self) -> None:
        self._refit(range(self.instances))
        self._count(range(self.instances))

    def _count(self, instances) -> None:
        self._per_instance.zero_()
        wp.launch(_crossing_kernel, dim=len(self._out), device=self.device,
                  inputs=[self._counted.of(instances), self._x, self._faces, self._edges, BOX_PAD, self.num_vertices],
                  outputs=[self._out, self._per_instance])

    def count_points(self, points: wp.array, instances=None) -> np.ndarray:
        """Crossing edges of every copy, int64 (instances,), at positions [m] already on the device:
        float32 points (instances * V,) vec3 (e.g. a batched cloth state's positions). instances:
        the copies to count (None: all); the others count 0 (a pool's idle slots; their BVHs are
        refit only inside the CUDA graph of :meth:`MeshIdSubset.refit`)."""
        chosen = tuple(range(self.instances)) if instances is None else tuple(sorted(int(k) for k in instances))
        if any(not 0 <= k < self.instances for k in chosen):
            raise InputError(f"instances {list(chosen)} are not all among the counter's {self.instances} copies")
        self.load(points, chosen)
        self._count(chosen)
        return self._per_instance.numpy().astype(np.int64)

    def crossing(self, positions) -> np.ndarray:
        """Which edges cross a triangle at one frame: bool (E,) over :attr:`edges`; positions [m] (V, 3)."""
        x = np.asarray(positions, dtype=np.float64)
        if self.instances != 1:
            raise InputError("crossing() takes one copy; a counter of several counts them with count_points()")
        if x.shape != (self.num_vertices, 3):
            raise InputError(f"positions must have shape ({self.num_vertices}, 3), got {x.shape}")
        if not np.all(np.isfinite(x)):
            raise InputError("positions contain NaN or inf")
        self._x.assign(x)
        self._points.assign(x.astype(np.float32))
        self._launch()
        return self._out.numpy() != 0

    def pairs(self, positions) -> np.ndarray:
        """Every (edge, triangle) that crosses at one frame: int64 (P, 2) of indices into
        :attr:`edges` and the faces, sorted; positions [m] (V, 3) of one copy."""
        self.crossing(positions)  # validates, loads the positions and builds or refits the BVH
        count = wp.zeros(1, dtype=wp.int32, device=self.device)
        capacity = max(64, 4 * int(self._per_instance.numpy()[0]))
        while True:
            out = wp.zeros((capacity, 2), dtype=wp.int32, device=self.device)
            count.zero_()
            wp.launch(_pairs_kernel, dim=len(self.edges), device=self.device,
                      inputs=[self._meshes[0].id, self._x, self._faces, self._edges, BOX_PAD],
                      outputs=[count, out])
            n = int(count.numpy()[0])
            if n <= capacity:
                found = out.numpy()[:n].astype(np.int64)
                return found[np.lexsort((found[:, 1], found[:, 0]))]
            capacity = n

    def count(self, positions) -> np.ndarray:
        """Crossing edges per frame, int64 (T,); positions [m] (T, V, 3) (or (V, 3): one frame)."""
        x = np.asarray(positions, dtype=np.float64)
        frames = x[None] if x.ndim == 2 else x
        return np.array([int(self.crossing(frame).sum()) for frame in frames], dtype=np.int64)


def crossing_edges(positions, faces, device: str = "cpu") -> np.ndarray:
    """The crossing edges of one frame, int32 (K, 2) vertex pairs; positions [m] (V, 3), faces (F, 3)."""
    counter = CrossingCounter(faces, len(positions), device)
    return counter.edges[counter.crossing(positions)]


def count_crossing_edges(positions, faces, device: str = "cpu") -> np.ndarray:
    """Crossing edges per frame, int64 (T,); positions [m] (T, V, 3) or (V, 3); faces (F, 3)."""
    x = np.asarray(positions)
    return CrossingCounter(faces, x.shape[-2], device).count(x)
