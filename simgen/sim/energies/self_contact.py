"""Cloth self-contact: vertex-triangle and edge-edge repulsion within a thickness, with gradient and PSD Hessian.

For a cloth vertex p and a triangle (a, b, c) of the same instance that does not contain p, with
d = |p - q| the distance to the triangle's closest point q = w_a a + w_b b + w_c c:

    E = k * max(thickness - d, 0)^p,    n = (p - q) / d,
    dE/dp = E'(d) n,   dE/da = -w_a E'(d) n  (and b, c alike),   E'(d) = -k p (thickness - d)^(p-1),

the gradient being exact (the closest point's own motion is orthogonal to n). Two edges (a, b) and
(c, d) that share no vertex take the same penalty of the distance between their closest points
a + s (b - a) and c + t (d - c), with weights (1 - s, s, -(1 - t), -t) in place of (1, -w_a, -w_b,
-w_c). Where a closest point is an edge's end, that contact is also a vertex-triangle one and
counts once per pair (the sum stays continuous; a vertex near an edge is pushed a little harder).
The Hessian is the Gauss-Newton k p (p-1) (thickness - d)^(p-2) J^T n n^T J of each pair, of which
only the four diagonal blocks are kept: the off-diagonal ones couple vertices that are not
neighbours in the mesh, outside the solver's fixed sparsity pattern. What is dropped makes the
Newton direction less stiff between the pair, never indefinite (each kept block is PSD), and the
guard still checks every step against the true energy. It is the same penalty shape as the body
contact (:mod:`.contact`), so its parameters read alike.

Candidates: once per substep (at its start, :meth:`SelfContactSet.update`), every vertex collects
up to ``max_candidates`` triangles whose closest point lies within ``search_radius`` (a BVH box
query), and every edge up to as many later edges within it (a second BVH over the edges). The
energy then re-evaluates the exact distances at every Newton iterate; a pair that only comes
within the thickness during the substep is seen at the next one, so search_radius must exceed the
thickness by the distance a vertex travels in one substep. The BVHs serve all instances: each
instance's vertices are shifted to its point of a lattice
(:func:`~simgen.sim.warp_toolkit.instance_offsets`) before the refit, and candidates of another
instance are skipped, so instances that overlap in space (same body, different shapes) never see
each other. Primitives that share a vertex are skipped; those of 1-ring neighbours are not, so the
mesh's edges must be several thicknesses long (they are ~2 cm on the library garments). What the
repulsion misses, no step carries through: :mod:`simgen.sim.impact_filter`.
"""

import functools
from types import SimpleNamespace

import numpy as np
import warp as wp

from simgen.params import SelfContactParams  # declared with the other terms' parameters, Warp-free
from simgen.sim.warp_toolkit import BVH_CONSTRUCTOR, instance_offsets, module_name, resolve_outputs, scalar_types
from simgen.body.surface_query import contact_funcs
from simgen.garment.mesh import unique_edges

__all__ = ["SelfContactParams", "SelfContactSet", "eval_self_contact", "self_contact_kernels"]



@functools.cache
def self_contact_kernels(scalar) -> SimpleNamespace:
    """Kernels for one scalar type: ``.shift`` (broad-phase points), ``.candidates`` (per-vertex
    triangle lists) and ``.repulsion`` (energy/gradient/Hessian), one thread per vertex."""
    T = scalar_types(scalar)
    vec3, mat33 = T.vec3, T.mat33
    closest_point_triangle = contact_funcs(scalar).closest_point_triangle
    closest_points_segments = contact_funcs(scalar).closest_points_segments
    mod = module_name(__name__, scalar)
    tiny = scalar(1.0e-12)
    one = scalar(1.0)

    @wp.func
    def add_pair(i0: int, i1: int, i2: int, i3: int, w0: scalar, w1: scalar, w2: scalar, w3: scalar,
                 diff: vec3, inst: int, diag_slots: wp.array(dtype=wp.int32), thickness: scalar, stiffness: scalar,
                 power: scalar, want_energy: int, want_grad: int, want_hess: int, energy: wp.array(dtype=scalar),
                 grad: wp.array(dtype=vec3), hess: wp.array(dtype=mat33)):
        # One pair's penalty k (thickness - d)^p of d = |diff|, diff = sum_k w_k x_{i_k} at fixed
        # closest points: energy, gradient and the four diagonal Gauss-Newton blocks.
        d = wp.length(diff)
        if d >= thickness or d <= tiny:
            return
        n = diff / d
        pen = thickness - d
        if want_energy != 0:
            wp.atomic_add(energy, inst, stiffness * wp.pow(pen, power))
        if want_grad != 0:
            g = (-stiffness * power * wp.pow(pen, power - one)) * n  # dE/d(diff)
            wp.atomic_add(grad, i0, w0 * g)
            wp.atomic_add(grad, i1, w1 * g)
            wp.atomic_add(grad, i2, w2 * g)
            wp.atomic_add(grad, i3, w3 * g)
        if want_hess != 0:
            nn = (stiffness * power * (power - one) * wp.pow(pen, power - scalar(2.0))) * wp.outer(n, n)
            wp.atomic_add(hess, diag_slots[i0], (w0 * w0) * nn)
            wp.atomic_add(hess, diag_slots[i1], (w1 * w1) * nn)
            wp.atomic_add(hess, diag_slots[i2], (w2 * w2) * nn)
            wp.atomic_add(hess, diag_slots[i3], (w3 * w3) * nn)

    @wp.kernel(enable_backward=False, module=mod)
    def shift(x: wp.array(dtype=vec3), vertex_instance: wp.array(dtype=wp.int32), offsets: wp.array(dtype=wp.vec3),
              points: wp.array(dtype=wp.vec3)):
        i = wp.tid()
        points[i] = wp.vec3(x[i]) + offsets[vertex_instance[i]]

    @wp.kernel(enable_backward=False, module=mod)
    def candidates(x: wp.array(dtype=vec3), vertex_instance: wp.array(dtype=wp.int32),
                   triangles: wp.array(dtype=wp.int32, ndim=2), mesh: wp.uint64, offsets: wp.array(dtype=wp.vec3),
                   radius: scalar, max_candidates: int, candidate: wp.array(dtype=wp.int32, ndim=2),
                   count: wp.array(dtype=wp.int32)):
        i = wp.tid()
        p = x[i]
        ps = wp.vec3(p) + offsets[vertex_instance[i]]
        r = float(radius)
        query = wp.mesh_query_aabb(mesh, ps - wp.vec3(r, r, r), ps + wp.vec3(r, r, r))
        face = int(0)
        n = int(0)
        while wp.mesh_query_aabb_next(query, face):
            if n >= max_candidates:
                break
            ia = triangles[face, 0]
            ib = triangles[face, 1]
            ic = triangles[face, 2]
            if ia == i or ib == i or ic == i or vertex_instance[ia] != vertex_instance[i]:
                continue
            q, bary, interior = closest_point_triangle(p, x[ia], x[ib], x[ic])
            if wp.length(p - q) < radius:
                candidate[i, n] = face
                n += 1
        count[i] = n

    @wp.kernel(enable_backward=False, module=mod)
    def repulsion(x: wp.array(dtype=vec3), vertex_instance: wp.array(dtype=wp.int32),
                  triangles: wp.array(dtype=wp.int32, ndim=2), candidate: wp.array(dtype=wp.int32, ndim=2),
                  count: wp.array(dtype=wp.int32), diag_slots: wp.array(dtype=wp.int32),
                  thickness: scalar, stiffness: scalar, power: scalar,
                  want_energy: int, want_grad: int, want_hess: int,
                  energy: wp.array(dtype=scalar), grad: wp.array(dtype=vec3), hess: wp.array(dtype=mat33)):
        i = wp.tid()
        p = x[i]
        for c in range(count[i]):
            face = candidate[i, c]
            ia = triangles[face, 0]
            ib = triangles[face, 1]
            ic = triangles[face, 2]
            q, w, interior = closest_point_triangle(p, x[ia], x[ib], x[ic])
            add_pair(i, ia, ib, ic, one, -w[0], -w[1], -w[2], p - q, vertex_instance[i], diag_slots, thickness,
                     stiffness, power, want_energy, want_grad, want_hess, energy, grad, hess)

    @wp.kernel(enable_backward=False, module=mod)
    def edge_boxes(x: wp.array(dtype=vec3), edges: wp.array(dtype=wp.int32, ndim=2),
                   vertex_instance: wp.array(dtype=wp.int32), offsets: wp.array(dtype=wp.vec3),
                   lowers: wp.array(dtype=wp.vec3), uppers: wp.array(dtype=wp.vec3)):
        e = wp.tid()
        shift = offsets[vertex_instance[edges[e, 0]]]
        a = wp.vec3(x[edges[e, 0]]) + shift
        b = wp.vec3(x[edges[e, 1]]) + shift
        lowers[e] = wp.min(a, b)
        uppers[e] = wp.max(a, b)

    @wp.kernel(enable_backward=False, module=mod)
    def edge_candidates(x: wp.array(dtype=vec3), vertex_instance: wp.array(dtype=wp.int32),
                        edges: wp.array(dtype=wp.int32, ndim=2), bvh: wp.uint64, lowers: wp.array(dtype=wp.vec3),
                        uppers: wp.array(dtype=wp.vec3), radius: scalar, max_candidates: int,
                        candidate: wp.array(dtype=wp.int32, ndim=2), count: wp.array(dtype=wp.int32)):
        e = wp.tid()
        a = edges[e, 0]
        b = edges[e, 1]
        r = float(radius)
        query = wp.bvh_query_aabb(bvh, lowers[e] - wp.vec3(r, r, r), uppers[e] + wp.vec3(r, r, r))
        f = int(0)
        n = int(0)
        while wp.bvh_query_next(query, f):
            if n >= max_candidates:
                break
            c = edges[f, 0]
            d = edges[f, 1]
            if f <= e or c == a or c == b or d == a or d == b or vertex_instance[c] != vertex_instance[a]:
                continue  # each pair once, from its lower edge
            s, t = closest_points_segments(x[a], x[b], x[c], x[d])
            if wp.length((x[a] + s * (x[b] - x[a])) - (x[c] + t * (x[d] - x[c]))) < radius:
                candidate[e, n] = f
                n += 1
        count[e] = n

    @wp.kernel(enable_backward=False, module=mod)
    def edge_repulsion(x: wp.array(dtype=vec3), vertex_instance: wp.array(dtype=wp.int32),
                       edges: wp.array(dtype=wp.int32, ndim=2), candidate: wp.array(dtype=wp.int32, ndim=2),
                       count: wp.array(dtype=wp.int32), diag_slots: wp.array(dtype=wp.int32),
                       thickness: scalar, stiffness: scalar, power: scalar,
                       want_energy: int, want_grad: int, want_hess: int,
                       energy: wp.array(dtype=scalar), grad: wp.array(dtype=vec3), hess: wp.array(dtype=mat33)):
        e = wp.tid()
        a = edges[e, 0]
        b = edges[e, 1]
        for k in range(count[e]):
            f = candidate[e, k]
            c = edges[f, 0]
            d = edges[f, 1]
            s, t = closest_points_segments(x[a], x[b], x[c], x[d])
            diff = (x[a] + s * (x[b] - x[a])) - (x[c] + t * (x[d] - x[c]))
            # d(diff)/d(x_a, x_b, x_c, x_d) at fixed s, t: 1 - s, s, t - 1, -t
            add_pair(a, b, c, d, one - s, s, t - one, -t, diff, vertex_instance[a], diag_slots, thickness,
                     stiffness, power, want_energy, want_grad, want_hess, energy, grad, hess)

    return SimpleNamespace(shift=shift, candidates=candidates, repulsion=repulsion, edge_boxes=edge_boxes,
                           edge_candidates=edge_candidates, edge_repulsion=edge_repulsion)


class SelfContactSet:
    """Broad-phase BVHs and candidate lists of one model (device buffers).

    candidate: (V, max_candidates) int32 global triangle indices, count: (V,) int32 valid entries;
    edges: (E, 2) int32 the garment edges, edge_candidate: (E, max_candidates) int32 indices of
    edges after the edge's own, edge_count: (E,) int32. :meth:`update` refits both BVHs at the given
    positions and refills the lists (capturable: kernel launches and BVH refits, no host reads).
    """

    def __init__(self, model, params: SelfContactParams) -> None:
        self.model = model
        self.params = params
        dev, n = model.device, model.num_vertices
        # The BVH's tree is built once, here, and only refit later: build it on the (shifted) rest
        # shape so its topology follows the garment (a tree built on coincident points would make
        # every box overlap every query).
        self.offsets = wp.array(instance_offsets(model.num_instances), dtype=wp.vec3, device=dev)
        shift = self.offsets.numpy()[np.asarray(model.host.vertex_instance)]
        rest = np.asarray(model.host.rest_positions, dtype=np.float64) + shift
        self.points = wp.array(rest.astype(np.float32), dtype=wp.vec3, device=dev)
        flat = wp.array(np.asarray(model.host.triangles, dtype=np.int32).reshape(-1), dtype=wp.int32, device=dev)
        self._indices = flat  # the BVH keeps a reference; it must outlive the mesh
        self.mesh = wp.Mesh(points=self.points, indices=flat, bvh_constructor=BVH_CONSTRUCTOR)
        self.candidate = wp.zeros((n, params.max_candidates), dtype=wp.int32, device=dev)
        self.count = wp.zeros(n, dtype=wp.int32, device=dev)
        edges = unique_edges(np.asarray(model.host.triangles)).astype(np.int32)
        self.edges = wp.array(edges, dtype=wp.int32, device=dev)
        self._lowers = wp.zeros(len(edges), dtype=wp.vec3, device=dev)
        self._uppers = wp.zeros(len(edges), dtype=wp.vec3, device=dev)
        self._edge_boxes(model.rest_positions)
        self.edge_bvh = wp.Bvh(self._lowers, self._uppers, constructor=BVH_CONSTRUCTOR)
        self.edge_candidate = wp.zeros((len(edges), params.max_candidates), dtype=wp.int32, device=dev)
        self.edge_count = wp.zeros(len(edges), dtype=wp.int32, device=dev)

    def _edge_boxes(self, positions) -> None:
        m = self.model
        wp.launch(self_contact_kernels(m.scalar).edge_boxes, dim=self.edges.shape[0], device=m.device,
                  inputs=[positions, self.edges, m.vertex_instance, self.offsets, self._lowers, self._uppers])

    def update(self, positions) -> None:
        """Gather candidate triangles and edges for ``positions`` [m], (V,) vec3 (a substep's start)."""
        m, p = self.model, self.params
        k = self_contact_kernels(m.scalar)
        wp.launch(k.shift, dim=m.num_vertices, device=m.device,
                  inputs=[positions, m.vertex_instance, self.offsets, self.points])
        self.mesh.refit()
        wp.launch(k.candidates, dim=m.num_vertices, device=m.device, inputs=[
            positions, m.vertex_instance, m.triangles, self.mesh.id, self.offsets, p.search_radius,
            p.max_candidates, self.candidate, self.count])
        self._edge_boxes(positions)
        self.edge_bvh.refit()
        wp.launch(k.edge_candidates, dim=self.edges.shape[0], device=m.device, inputs=[
            positions, m.vertex_instance, self.edges, self.edge_bvh.id, self._lowers, self._uppers, p.search_radius,
            p.max_candidates, self.edge_candidate, self.edge_count])


def eval_self_contact(model, positions, contact_set: SelfContactSet, *, energy=None, gradient=None, hessian=None,
                      scale: float = 1.0) -> None:
    """Accumulate the vertex-triangle and edge-edge repulsion over the candidates of ``contact_set``.

    positions [m], (V,) vec3. Outputs (added to, optional): energy [J] per instance; gradient [J/m]
    (V,) vec3; hessian (diagonal blocks, PSD; the model's BsrMatrix or its values). scale
    multiplies all three.
    """
    we, wg, wh, e, g, h = resolve_outputs(energy, gradient, hessian)
    if not (we or wg or wh):
        return
    p, k = contact_set.params, self_contact_kernels(model.scalar)
    tail = [model.diag_slots, p.thickness, p.stiffness * scale, p.power, we, wg, wh, e, g, h]
    wp.launch(k.repulsion, dim=model.num_vertices, device=model.device, inputs=[
        positions, model.vertex_instance, model.triangles, contact_set.candidate, contact_set.count, *tail])
    wp.launch(k.edge_repulsion, dim=contact_set.edges.shape[0], device=model.device, inputs=[
        positions, model.vertex_instance, contact_set.edges, contact_set.edge_candidate, contact_set.edge_count, *tail])
