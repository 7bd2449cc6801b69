"""The frame's last step with self-contact on: find cloth that passed through itself, untangle it.

Self-contact keeps layers apart and the impact filter stops most paths through cloth
(:mod:`simgen.sim.impact_filter`), but a substep can still end tangled (a slip of the solver or the
body projection, or any path at all with the filter off). At the end of every frame,
:class:`TangleRepair` counts each busy instance's crossing edges on the device
(:mod:`simgen.garment.crossings`) and untangles the instances that have some before the frame is
recorded: first up to ``DEVICE_ROUNDS`` rounds on the device of the history rule (each crossing
edge sends back through the triangle's plane the vertex that has left the side where both its ends
lay at the frame's start; the one nearer the plane where they did not), then, for whatever is left,
:func:`simgen.garment.untangle.untangle` on the host (the graph cut as well). A moved vertex keeps
its velocity except the part that pointed back through the layer it was moved out of, so the next
substep does not push it straight back. ``repaired`` counts, per instance, the frames that needed
it; ``left`` the crossing edges that remained at its last repair.
"""

from __future__ import annotations

import numpy as np
import warp as wp

from simgen.garment.crossings import BOX_PAD, CrossingCounter, edge_query, segment_crosses_triangle
from simgen.garment.untangle import untangle

#: [m] how far beyond the crossed triangle's plane a vertex is put back.
MARGIN = 5.0e-4
#: device rounds of the history rule per frame before the host's untangling takes what is left.
DEVICE_ROUNDS = 8
#: the host's rounds per instance and frame: a tangle they cannot remove is left to the next frame's
#: repair (and counted in ``left``) instead of stalling the batch.
HOST_ROUNDS = 20


@wp.func
def _side(u: wp.vec3d, a: wp.vec3d, b: wp.vec3d, c: wp.vec3d) -> wp.float64:
    return wp.dot(u - a, wp.cross(b - a, c - a))


@wp.kernel(enable_backward=False)
def _push_back(meshes: wp.array(dtype=wp.uint64), x: wp.array(dtype=wp.vec3d), ref: wp.array(dtype=wp.vec3),
               faces: wp.array(dtype=wp.int32, ndim=2), edges: wp.array(dtype=wp.int32, ndim=2), pad: float,
               num_vertices: int, margin: float, pinned: wp.array(dtype=wp.int32), active: wp.array(dtype=wp.int32),
               accum: wp.array(dtype=wp.vec3d), hits: wp.array(dtype=wp.int32), found: wp.array(dtype=wp.int32)):
    # Thread = (instance, edge). For every triangle the edge crosses: the vertex that left the side
    # where both ends lay at the frame's start (else the one nearer the plane) is sent back through
    # the plane, margin beyond it; a pinned one stays and the triangle moves instead.
    tid = wp.tid()
    num_edges = edges.shape[0]
    instance = tid / num_edges
    if active[instance] == 0:
        return
    base = instance * num_vertices
    i = edges[tid - instance * num_edges, 0] + base
    j = edges[tid - instance * num_edges, 1] + base
    p = x[i]
    q = x[j]
    query = edge_query(meshes[instance], p, q, pad)
    f = int(0)
    zero = wp.float64(0.0)
    while wp.mesh_query_aabb_next(query, f):
        a = faces[f, 0] + base
        b = faces[f, 1] + base
        c = faces[f, 2] + base
        if a == i or a == j or b == i or b == j or c == i or c == j:
            continue
        if segment_crosses_triangle(p, q, x[a], x[b], x[c]) == 0:
            continue
        found[0] = 1
        n = wp.normalize(wp.cross(x[b] - x[a], x[c] - x[a]))
        dp = wp.dot(p - x[a], n)
        dq = wp.dot(q - x[a], n)
        ra = wp.vec3d(ref[a])
        rb = wp.vec3d(ref[b])
        rc = wp.vec3d(ref[c])
        sp = _side(wp.vec3d(ref[i]), ra, rb, rc)
        sq = _side(wp.vec3d(ref[j]), ra, rb, rc)
        p_in = wp.abs(dp) <= wp.abs(dq)
        if sp * sq > zero:
            p_in = (dp > zero) != (sp > zero)
        inside = j
        d_in = dq
        d_out = dp
        if p_in:
            inside = i
            d_in = dp
            d_out = dq
        depth = wp.float64(margin) - d_in
        if d_out < zero:
            depth = -wp.float64(margin) - d_in
        if pinned[inside] == 0:
            wp.atomic_add(accum, inside, depth * n)
            wp.atomic_add(hits, inside, 1)
        else:
            for k in range(3):
                v = faces[f, k] + base
                if pinned[v] == 0:
                    wp.atomic_add(accum, v, -depth * n)
                    wp.atomic_add(hits, v, 1)


@wp.kernel(enable_backward=False)
def _apply_pushes(accum: wp.array(dtype=wp.vec3d), hits: wp.array(dtype=wp.int32), x: wp.array(dtype=wp.vec3),
                  v: wp.array(dtype=wp.vec3)):
    # Each pushed vertex moves by the mean of its pushes and keeps no velocity back along it.
    i = wp.tid()
    if hits[i] == 0:
        return
    d = wp.vec3(accum[i] / wp.float64(hits[i]))
    x[i] = x[i] + d
    length = wp.length(d)
    if length > 0.0:
        u = d / length
        back = wp.dot(v[i], u)
        if back < 0.0:
            v[i] = v[i] - back * u
    accum[i] = wp.vec3d()
    hits[i] = 0

__all__ = ["TangleRepair"]


class TangleRepair:
    """Untangles the instances of a batched cloth state at frame ends (module doc).

    faces (F, 3): one copy's triangles; num_vertices V of one copy; instances N; device: the state's.
    """

    def __init__(self, faces, num_vertices: int, instances: int, device) -> None:
        self.faces = np.asarray(faces)
        self.num_vertices, self.instances = int(num_vertices), int(instances)
        self.counter = CrossingCounter(self.faces, self.num_vertices, str(device), instances=self.instances)
        self.single = CrossingCounter(self.faces, self.num_vertices, str(device))
        self.repaired = np.zeros(self.instances, dtype=np.int64)
        self.left = np.zeros(self.instances, dtype=np.int64)
        self._active = None   # device buffers of the pushes (_buffers), made on first use

    def __call__(self, state, pinned: wp.array, active: np.ndarray, reference: wp.array | None = None) -> list[int]:
        """Untangle the ``active`` (bool (N,)) instances of ``state`` (positions [m], velocities
        [m/s], (N V,) vec3 float32) that cross themselves; ``pinned`` (N V,) int: vertices that stay;
        ``reference`` (N V,) vec3 [m]: the frame's start, whose sides tell which vertex went through.
        Returns the instances moved."""
        counts = self.counter.count_points(state.positions)
        todo = np.flatnonzero((counts > 0) & np.asarray(active, dtype=bool))
        if not len(todo):
            return []
        self.repaired[todo] += 1
        if reference is not None:
            self._device_rounds(state, pinned, todo, reference)
            counts = self.counter.count_points(state.positions)
        left = [k for k in todo if counts[k] > 0]
        if left:
            self._host(state, pinned, left, reference)
        self.left[todo] = self.counter.count_points(state.positions)[todo] if left else 0
        return todo.tolist()

    def _buffers(self, device) -> None:
        """The device buffers of the pushes, made on first use."""
        if self._active is None:
            n = self.instances * self.num_vertices
            self._active = wp.zeros(self.instances, dtype=wp.int32, device=device)
            self._accum = wp.zeros(n, dtype=wp.vec3d, device=device)
            self._hits = wp.zeros(n, dtype=wp.int32, device=device)
            self._found = wp.zeros(1, dtype=wp.int32, device=device)

    def _device_rounds(self, state, pinned, todo, reference) -> None:
        """Up to DEVICE_ROUNDS rounds of the history rule (module doc) on the device, for ``todo``."""
        dev = state.positions.device
        self._buffers(dev)
        flags = np.zeros(self.instances, dtype=np.int32)
        flags[todo] = 1
        self._active.assign(flags)
        c = self.counter
        for _ in range(DEVICE_ROUNDS):
            self._found.zero_()
            wp.launch(_push_back, dim=self.instances * len(c.edges), device=dev,
                      inputs=[c.mesh_ids, c.x64, reference, c.device_faces, c.device_edges, BOX_PAD,
                              self.num_vertices, MARGIN, pinned, self._active, self._accum, self._hits, self._found])
            wp.launch(_apply_pushes, dim=len(self._hits), device=dev,
                      inputs=[self._accum, self._hits, state.positions, state.velocities])
            if not self._found.numpy()[0]:
                return
            c.load(state.positions)

    def _host(self, state, pinned, todo, reference) -> None:
        """Untangle ``todo`` on the host (graph cut, with the reference where it tells); the shifts
        are applied on the device like the device rounds' pushes."""
        dev = state.positions.device
        self._buffers(dev)
        x, fixed = state.positions.numpy().astype(np.float64), pinned.numpy() != 0
        ref = None if reference is None else reference.numpy()
        shift = np.zeros_like(x)
        V = self.num_vertices
        for k in todo:
            rows = slice(k * V, (k + 1) * V)
            result = untangle(x[rows], self.faces, pinned=fixed[rows], counter=self.single,
                              reference=None if ref is None else ref[rows], max_rounds=HOST_ROUNDS)
            shift[rows] = result.positions - x[rows]
        self._accum.assign(shift)
        self._hits.assign(np.any(shift != 0.0, axis=1).astype(np.int32))
        wp.launch(_apply_pushes, dim=len(self._hits), device=dev,
                  inputs=[self._accum, self._hits, state.positions, state.velocities])
