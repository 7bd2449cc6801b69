"""The body-surface query, specified once, and its Warp implementation (CPU or CUDA, float32 or float64).

Every closest-point, signed-distance and inside/outside question asked of a body (or any closed,
outward-oriented triangle mesh) follows this one specification. Its torch twin is
:mod:`simgen.physics.surface_query`; tests/test_body_surface_query.py holds the two equal.

Closest face: the triangle nearest to the point x [m], picked by Warp's float32 BVH query among
those within ``query_distance`` [m] (a point farther from every triangle finds none; of faces
equally near within float32 resolution, either).

Closest point c: the exact point of that triangle nearest to x (Ericson, *Real-Time Collision
Detection* 5.1.5: the Voronoi regions of its vertices, its edges and its face, tested in that
order), recomputed in the caller's scalar type (float32 or float64) on the triangle's corners.

Signed distance d [m] (< 0 inside) and normal n = grad d (unit, outward): where c lies inside the
face, d = (x - a) . n_f, the plane distance along the unit face normal n_f (linear in x) and
n = n_f; at an edge or a vertex, d = s |x - c| and n = s (x - c) / |x - c| (n_f where x is on the
surface), the same from either face of an edge, so d is continuous where the chosen face changes.
Always c = x - d n.

The sign s, two variants (argument ``winding``):

- pseudo-normal (winding = 0): s from the angle-weighted pseudo-normal of the closest feature
  (``warp.mesh_query_point_sign_normal``); inside a face it is the plane's side. Local, so d and n
  come from the same feature and d is C1 across the surface; no winding-number tree to refit.
  Where the posed body intersects itself (armpits, crotch) it answers for the nearer surface, so
  cloth is pushed out of that surface instead of across the other limb. It misclassifies a point
  past the medial axis of a thin part. Used by the solver's contact energy, its friction frame and
  its projection (:mod:`simgen.sim`), by the collision post-process of the learned models
  (:mod:`simgen.learn.collision`), and in torch by the losses (:mod:`simgen.physics`).
- winding number (winding = 1): inside where the generalised winding number exceeds 1/2
  (``warp.mesh_query_point_sign_winding_number``; the mesh needs ``support_winding_number``), also
  inside a face: d = s |d_plane|. Right where body parts overlap, where a face's plane reads the
  other part's inside as outside. Used by the audits: :func:`simgen.body.surface.project_to_surface`
  (garment checks, skinning weights, remeshing, motion clearance, the learned models' inside
  fraction), the frame statistics and the dataset check (:data:`classify_inside`).

Body part rule (:func:`contact_funcs` ``body_contact``; pseudo-normal sign). A skinned body without
pose correctives intersects itself wherever a limb presses against it (arms sinking into the torso
in a rest pose, thighs at the crotch), and cloth caught between the two parts cannot end outside
both. The closest surface then belongs to the part that is pressing in, and pushing the cloth out
of it moves the cloth across that part: torso cloth ends outside the forearm, so the arm is inside
the shirt, and the arms leave the sleeves. With body part labels (:mod:`simgen.body.parts`: one bit
mask of parts per body face, one home part per cloth vertex, taken from the garment's skinning
weights), the closest face is taken from the vertex's own part instead whenever the vertex is
inside the body at a face that belongs to another part only, and a face of the own part lies
within ``pinch_distance`` [m] (the sign then from that face's plane: the plane distance inside the
face, the side of its plane at an edge or vertex): cloth lying on its own part keeps to it and the
pressing part passes through it. Cloth outside the body collides with whatever surface is closest,
whichever part it belongs to (cloth resting on the deltoid where skinning folds it over the torso
at the shoulder must stay on it), and so does cloth farther than ``pinch_distance`` from its own
part (a loose dress hit by a leg). Faces near the seam between two parts (the shoulder, the hip)
belong to both, so cloth sliding across a seam sees one continuous surface.

Self-intersection rule of the statistics (:data:`classify_inside`). A point inside the body (winding
number) is *at a body self-intersection* when its closest point, moved ``probe`` [m] along n
(:data:`SELF_INTERSECTION_PROBE`, 2 mm), is
still inside (the closest surface is buried in another part), or when the part rule sees it outside
(cloth that the contact keeps on its own part where another part presses into it).
"""

import functools
from types import SimpleNamespace

import numpy as np
import warp as wp

from simgen.errors import InputError

__all__ = ["contact_funcs", "query_kernel", "nearest_face_kernel", "classify_inside", "SELF_INTERSECTION_PROBE",
           "MeshIdSubset"]

#: [m] outward offset of the self-intersection rule's probe (module doc).
SELF_INTERSECTION_PROBE = 2.0e-3


class MeshIdSubset:
    """The ids of one warp.Mesh per instance on the device, with 0 for the instances outside a
    chosen subset (:data:`classify_inside` and the crossing counter skip an id of 0: a pool's idle
    slots). meshes: the warp.Mesh list; device: its Warp device."""

    def __init__(self, meshes: list, device) -> None:
        self.meshes = list(meshes)
        self.chosen = tuple(range(len(self.meshes)))
        self.device = wp.get_device(device)
        self.ids = wp.array([m.id for m in self.meshes], dtype=wp.uint64, device=self.device)
        self._refits = None   # CUDA: the graph of every mesh's refit

    def refit(self, chosen) -> None:
        """Refit the BVHs of the meshes ``chosen`` (instance indices) to their points. On CUDA, when
        more than an eighth of the meshes are chosen, all of them are refit by one CUDA graph recorded
        at the first such call, which spares the Python launches of a handful of kernels per mesh
        (about 9 of the 32 ms that a pool's 128 slots took one by one; the rest is the refits' GPU
        work: BENCHMARKS.md); idle meshes are refit too but never queried (id 0). Fewer are refit one
        by one. The graph holds each mesh's points array and BVH: they are updated in place, never
        replaced."""
        chosen = list(chosen)
        if not self.device.is_cuda or 8 * len(chosen) <= len(self.meshes):
            for k in chosen:
                self.meshes[k].refit()
            return
        if self._refits is None:
            with wp.ScopedCapture(device=self.device, force_module_load=False) as capture:
                for m in self.meshes:
                    m.refit()
            self._refits = capture.graph
        wp.capture_launch(self._refits)

    def of(self, chosen) -> wp.array:
        """(I,) uint64 ids, 0 outside ``chosen`` (instance indices); rewritten only when it changes."""
        chosen = tuple(int(k) for k in chosen)
        if chosen != self.chosen:
            bad = [k for k in chosen if not 0 <= k < len(self.meshes)]
            if bad:
                raise InputError(f"instance {bad[0]} is not one of the {len(self.meshes)} instances")
            ids = np.zeros(len(self.meshes), dtype=np.uint64)
            for k in chosen:
                ids[k] = self.meshes[k].id
            self.ids.assign(ids)
            self.chosen = chosen
        return self.ids


@functools.cache
def contact_funcs(scalar) -> SimpleNamespace:
    """Warp functions of the body-surface query (module doc) for one scalar type (wp.float32/64).

    Positions x and corners [m] are ``wp.types.vector(3, scalar)``; meshes are warp.Mesh ids
    (uint64, float32 points, watertight, counter-clockwise seen from outside); ``winding`` (int)
    picks the sign (0: pseudo-normal, 1: winding number).

    closest_point_triangle(p, a, b, c) -> (closest, barycentric weights of a, b, c, interior flag).
    closest_points_segments(p1, q1, p2, q2) -> (s, t): the closest points p1 + s (q1 - p1) and
      p2 + t (q2 - p2) of two segments, s and t in [0, 1] (Ericson, Real-Time Collision Detection,
      5.1.9; parallel segments get one of their closest pairs).
    closest_face(mesh, x, query_distance, winding) -> (found, face, s): the BVH query; s = +-1.
    face_distance(x, a, b, c, s, winding) -> (d, n, closest, bary) on the triangle (a, b, c) given
      the sign s (+-1; 0: the side of the triangle's plane).
    body_distance(mesh, x, query_distance, winding) -> (found, d, n, face, u, v): found is 1 if a
      face lies within query_distance; u, v (float32) the weights of the face's first two corners
      (as warp.mesh_eval_position/velocity take them).
    part_distance(mesh, part_masks, part_bit, x, radius) -> as body_distance, over the faces whose
      mask has part_bit within the box x +- radius only (found 0 if none is closer than radius),
      the sign from the face's plane.
    body_contact(mesh, part_masks, home, x, query_distance, pinch_distance) -> as body_distance
      (pseudo-normal) with the part rule for a vertex of home part ``home`` (-1: none), plus a last
      value ``own``: 1 where the own part's surface was taken.
    held_contact(mesh, part_masks, home, x, query_distance, pinch_distance, own) -> as
      body_distance (pseudo-normal), with the rule's choice given: own = 1 takes the own part's
      surface within pinch_distance (found 0 beyond), 0 the closest surface of the whole body.
    """
    vec3 = wp.types.vector(3, scalar)
    zero = scalar(0.0)
    one = scalar(1.0)
    tiny = scalar(1.0e-12)

    @wp.func
    def closest_point_triangle(p: vec3, a: vec3, b: vec3, c: vec3):
        ab = b - a
        ac = c - a
        ap = p - a
        d1 = wp.dot(ab, ap)
        d2 = wp.dot(ac, ap)
        if d1 <= zero and d2 <= zero:
            return a, vec3(one, zero, zero), 0
        bp = p - b
        d3 = wp.dot(ab, bp)
        d4 = wp.dot(ac, bp)
        if d3 >= zero and d4 <= d3:
            return b, vec3(zero, one, zero), 0
        vc = d1 * d4 - d3 * d2
        if vc <= zero and d1 >= zero and d3 <= zero:
            t = d1 / (d1 - d3)
            return a + t * ab, vec3(one - t, t, zero), 0
        cp = p - c
        d5 = wp.dot(ab, cp)
        d6 = wp.dot(ac, cp)
        if d6 >= zero and d5 <= d6:
            return c, vec3(zero, zero, one), 0
        vb = d5 * d2 - d1 * d6
        if vb <= zero and d2 >= zero and d6 <= zero:
            t = d2 / (d2 - d6)
            return a + t * ac, vec3(one - t, zero, t), 0
        va = d3 * d6 - d5 * d4
        if va <= zero and d4 - d3 >= zero and d5 - d6 >= zero:
            t = (d4 - d3) / ((d4 - d3) + (d5 - d6))
            return b + t * (c - b), vec3(zero, one - t, t), 0
        denom = one / (va + vb + vc)
        v = vb * denom
        w = vc * denom
        return a + v * ab + w * ac, vec3(one - v - w, v, w), 1

    @wp.func
    def closest_face(mesh: wp.uint64, x: vec3, query_distance: float, winding: int):
        xf = wp.vec3(x)
        s = one
        if winding != 0:
            w = wp.mesh_query_point_sign_winding_number(mesh, xf, query_distance)
            if w.sign < 0.0:
                s = -one
            return w.result, w.face, s
        q = wp.mesh_query_point_sign_normal(mesh, xf, query_distance)
        if q.sign < 0.0:
            s = -one
        return q.result, q.face, s

    @wp.func
    def face_distance(x: vec3, a: vec3, b: vec3, c: vec3, s: scalar, winding: int):
        nf = wp.normalize(wp.cross(b - a, c - a))
        q, bary, interior = closest_point_triangle(x, a, b, c)
        if interior != 0:
            # Closest point inside the face: d is the (linear) plane distance, n the face normal.
            d = wp.dot(x - a, nf)
            if winding != 0 and d * s < zero:
                return -d, -nf, q, bary
            return d, nf, q, bary
        diff = x - q
        dist = wp.length(diff)
        sign = s
        if s == zero:
            sign = one
            if wp.dot(diff, nf) < zero:
                sign = -one
        if dist > tiny:
            return sign * dist, (sign / dist) * diff, q, bary
        return zero, nf, q, bary

    @wp.func
    def mesh_face_distance(mesh: wp.uint64, face: int, x: vec3, s: scalar, winding: int):
        d, n, q, bary = face_distance(x, vec3(wp.mesh_get_point(mesh, face * 3 + 0)),
                                      vec3(wp.mesh_get_point(mesh, face * 3 + 1)),
                                      vec3(wp.mesh_get_point(mesh, face * 3 + 2)), s, winding)
        return d, n, q, bary

    @wp.func
    def body_distance(mesh: wp.uint64, x: vec3, query_distance: float, winding: int):
        # The float32 BVH query only picks the closest face (and the sign); the distance is then
        # recomputed exactly on that face in the scalar type.
        found, face, s = closest_face(mesh, x, query_distance, winding)
        if not found:
            return 0, zero, vec3(), -1, float(0.0), float(0.0)
        d, n, q, bary = mesh_face_distance(mesh, face, x, s, winding)
        return 1, d, n, face, float(bary[0]), float(bary[1])

    @wp.func
    def part_distance(mesh: wp.uint64, part_masks: wp.array(dtype=wp.int32), part_bit: int, x: vec3,
                      radius: float):
        xf = wp.vec3(x)
        query = wp.mesh_query_aabb(mesh, xf - wp.vec3(radius), xf + wp.vec3(radius))
        f = int(0)
        best_face = int(-1)
        best = scalar(radius)
        while wp.mesh_query_aabb_next(query, f):
            if (part_masks[f] & part_bit) != 0:
                c, bary, interior = closest_point_triangle(
                    x, vec3(wp.mesh_get_point(mesh, f * 3 + 0)), vec3(wp.mesh_get_point(mesh, f * 3 + 1)),
                    vec3(wp.mesh_get_point(mesh, f * 3 + 2)))
                dist = wp.length(x - c)
                if dist < best:
                    best = dist
                    best_face = f
        if best_face < 0:
            return 0, zero, vec3(), -1, float(0.0), float(0.0)
        d, n, q, bary = mesh_face_distance(mesh, best_face, x, zero, 0)
        return 1, d, n, best_face, float(bary[0]), float(bary[1])

    @wp.func
    def body_contact(mesh: wp.uint64, part_masks: wp.array(dtype=wp.int32), home: int, x: vec3,
                     query_distance: float, pinch_distance: float):
        found, d, n, face, u, v = body_distance(mesh, x, query_distance, 0)
        if found != 0 and home >= 0 and d < zero:
            bit = int(1) << home
            if (part_masks[face] & bit) == 0:
                # The closest face is another part's: near the own part, that part wins (module doc).
                own, d_own, n_own, face_own, u_own, v_own = part_distance(mesh, part_masks, bit, x, pinch_distance)
                if own != 0:
                    return own, d_own, n_own, face_own, u_own, v_own, 1
        return found, d, n, face, u, v, 0

    @wp.func
    def held_contact(mesh: wp.uint64, part_masks: wp.array(dtype=wp.int32), home: int, x: vec3,
                     query_distance: float, pinch_distance: float, own: int):
        if own != 0 and home >= 0:
            f1, d1, n1, face1, u1, v1 = part_distance(mesh, part_masks, int(1) << home, x, pinch_distance)
            return f1, d1, n1, face1, u1, v1
        f0, d0, n0, face0, u0, v0 = body_distance(mesh, x, query_distance, 0)
        return f0, d0, n0, face0, u0, v0

    @wp.func
    def closest_points_segments(p1: vec3, q1: vec3, p2: vec3, q2: vec3):
        d1 = q1 - p1
        d2 = q2 - p2
        r = p1 - p2
        a = wp.dot(d1, d1)
        e = wp.dot(d2, d2)
        f = wp.dot(d2, r)
        s = zero
        t = zero
        if a <= tiny and e <= tiny:
            return s, t
        if a <= tiny:
            t = wp.clamp(f / e, zero, one)
        else:
            c = wp.dot(d1, r)
            if e <= tiny:
                s = wp.clamp(-c / a, zero, one)
            else:
                b = wp.dot(d1, d2)
                denom = a * e - b * b
                if denom > tiny * a * e:
                    s = wp.clamp((b * f - c * e) / denom, zero, one)
                t = (b * s + f) / e
                if t < zero:
                    t = zero
                    s = wp.clamp(-c / a, zero, one)
                elif t > one:
                    t = one
                    s = wp.clamp((b - c) / a, zero, one)
        return s, t

    return SimpleNamespace(closest_point_triangle=closest_point_triangle,
                           closest_points_segments=closest_points_segments, closest_face=closest_face,
                           face_distance=face_distance, body_distance=body_distance, part_distance=part_distance,
                           body_contact=body_contact, held_contact=held_contact)


@functools.cache
def query_kernel(scalar):
    """The query of points on a mesh, one thread per point, for one scalar type.

    Inputs: mesh (warp.Mesh id: the BVH and the sign), vertices [m] (V,) vec3 of ``scalar`` and
    faces (F, 3) int32 (the same triangles: the distance is recomputed on these corners), points
    [m] (P,) vec3, query_distance [m] (float), winding (int: 0 pseudo-normal, 1 winding number).
    Outputs (P,): distance [m] (scalar; query_distance where no face is that close), normal (vec3,
    zero where none), closest [m] (vec3, the point itself where none), face (int32, -1 where none),
    bary (vec3: the weights of the face's three corners at the closest point).
    """
    vec3 = wp.types.vector(3, scalar)
    f = contact_funcs(scalar)
    closest_face, face_distance = f.closest_face, f.face_distance

    @wp.kernel(enable_backward=False, module=f"{__name__}.{scalar.__name__}")
    def query(mesh: wp.uint64, vertices: wp.array(dtype=vec3), faces: wp.array(dtype=wp.int32, ndim=2),
              points: wp.array(dtype=vec3), query_distance: float, winding: int,
              distance: wp.array(dtype=scalar), normal: wp.array(dtype=vec3), closest: wp.array(dtype=vec3),
              face: wp.array(dtype=wp.int32), bary: wp.array(dtype=vec3)):
        i = wp.tid()
        x = points[i]
        found, k, s = closest_face(mesh, x, query_distance, winding)
        if not found:
            distance[i] = scalar(query_distance)
            normal[i] = vec3()
            closest[i] = x
            face[i] = -1
            bary[i] = vec3()
            return
        d, n, c, b = face_distance(x, vertices[faces[k, 0]], vertices[faces[k, 1]], vertices[faces[k, 2]], s,
                                   winding)
        distance[i] = d
        normal[i] = n
        closest[i] = c
        face[i] = k
        bary[i] = b

    return query


@wp.kernel(enable_backward=False)
def nearest_face_kernel(meshes: wp.array(dtype=wp.uint64), points: wp.array(dtype=wp.vec3), per_mesh: int,
                        face: wp.array(dtype=wp.int32)):
    """The closest face (module doc, no query distance) of every point [m] (P,) on the mesh
    ``meshes[i // per_mesh]`` of its block of ``per_mesh`` points: the torch twin's batched
    nearest-triangle search. face (P,) int32: the triangle index (-1 if the query found none)."""
    i = wp.tid()
    q = wp.mesh_query_point_no_sign(meshes[i // per_mesh], points[i], 1.0e6)
    if q.result:
        face[i] = q.face
    else:
        face[i] = -1


_f32 = contact_funcs(wp.float32)
_body_distance, _body_contact = _f32.body_distance, _f32.body_contact


@wp.kernel(enable_backward=False)
def classify_inside(
    x: wp.array(dtype=wp.vec3),
    vertex_instance: wp.array(dtype=wp.int32),
    winding_meshes: wp.array(dtype=wp.uint64),
    query_distance: float,
    probe: float,
    vertex_part: wp.array(dtype=wp.int32),
    part_masks: wp.array(dtype=wp.int32),
    use_parts: int,
    pinch_distance: float,
    distance: wp.array(dtype=wp.float32),
    depth: wp.array(dtype=wp.float32),
    inside: wp.array(dtype=wp.int32),
    self_hit: wp.array(dtype=wp.int32),
):
    """Inside test and self-intersection rule (module doc), one thread per point.

    x [m] (P,) points; vertex_instance (P,) index into winding_meshes (warp.Mesh ids built with
    support_winding_number; 0: the point is not classified, its outputs stay those of a point far
    outside); query_distance, probe, pinch_distance [m]; vertex_part (P,) home parts
    and part_masks (Fb,) face part masks, read when use_parts != 0. Outputs (P,): distance [m] the
    unsigned distance to the surface (query_distance where farther), depth [m] that distance where
    inside (else 0), inside and self_hit (0/1).
    """
    i = wp.tid()
    distance[i] = query_distance
    depth[i] = 0.0
    inside[i] = 0
    self_hit[i] = 0
    xi = x[i]
    mesh = winding_meshes[vertex_instance[i]]
    if mesh == wp.uint64(0):
        return
    found, d, n, face, u, v = _body_distance(mesh, xi, query_distance, 1)
    if found == 0:
        return
    distance[i] = wp.abs(d)
    if d >= 0.0:
        return
    depth[i] = -d
    inside[i] = 1
    # The closest point x - d n, moved ``probe`` outward along n.
    out, d_out, n_out, f_out, u_out, v_out = _body_distance(mesh, xi - d * n + probe * n, query_distance + probe, 1)
    if out != 0 and d_out < 0.0:
        self_hit[i] = 1
    elif use_parts != 0:
        own, d_own, n_own, f_own, u_own, v_own, took = _body_contact(mesh, part_masks, vertex_part[i], xi,
                                                                      query_distance, pinch_distance)
        if own != 0 and d_own >= 0.0:
            self_hit[i] = 1
