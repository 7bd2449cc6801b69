"""Body contact penalty (SNUG eq. 5.12) inside a margin, with gradient and PSD Hessian.

Per cloth vertex v with signed distance d to its instance's body surface:

    E_v = k * max(margin - d, 0)^p,   grad = -k p (margin - d)^(p-1) n,
    Hessian = k p (p-1) (margin - d)^(p-2) n n^T   (PSD; exact where the closest point lies inside
    a body triangle, where d is linear in x; the curvature term of d at body edges and vertices is
    dropped, Gauss-Newton, because it is indefinite),

n = grad(d), the outward contact normal. Parameters (:class:`ContactParams`): margin [m] (SNUG:
2 mm), stiffness k [J/m^p], power p (SNUG: 3). SNUG trains with k = 250 J/m^3
(:meth:`ContactParams.snug`); the solver defaults to k = 1e4 J/m^3: a T-shirt vertex (~5e-5 kg)
that the body pushes 1 cm within one 1/300 s substep needs an inertial force m d/h^2 ~ 0.04 N;
3 k (margin - d)^2 = 0.04 N with k = 1e4 stops it 1.2 mm inside the margin, 0.8 mm outside the
body (with 250 J/m^3 it would end 5 mm inside the body), while the contact Hessian 6 k (margin - d) ~ 70
N/m stays of the order of the mass (~4 N/m) and membrane (~10 N/m) terms, so Newton/PCG stay well
conditioned.

Signed distance: ``warp.mesh_query_point_sign_normal`` (closest point, sign from the angle-weighted
pseudo-normal of the closest feature), not the winding-number variant: it is the cheaper query
(no winding-number tree to refit and traverse each substep), it is local, so d and n come from the
same closest feature and the energy is C1 across the surface, and where the posed body intersects
itself (armpits, crotch) it pushes the cloth out of the nearer surface instead of across the other
limb, as a winding number would. It needs a watertight, outward-oriented body (the SMPL/anny skin
is), and it misclassifies a vertex that went past the medial axis of a thin limb (> its half
thickness, several cm) in one step, which these step sizes and stiffnesses make unlikely; outputs can
still be audited with winding numbers (:func:`simgen.body.surface.project_to_surface`).
The query (float32) only picks the closest face and the sign; the distance is recomputed exactly
on that face in the kernel's scalar type: the plane distance where the closest point is interior to
the face, the point distance at its edges and vertices (the same on either face of an edge, so d
stays continuous where the chosen face changes).

Bodies: one warp.Mesh per instance (bodies of different instances overlap in space), passed as a
(num_instances,) uint64 array of mesh ids indexed by the vertex's instance; id 0 = no body.

Where the body meets itself. A skinned body without pose correctives intersects itself wherever a
limb presses against it (arms sinking into the torso in a rest pose, thighs at the crotch), and
cloth caught between the two parts cannot end outside both. The closest surface then belongs to
the part that is pressing in, and pushing the cloth out of it moves the cloth across that part:
torso cloth ends outside the forearm, so the arm is inside the shirt, and the arms leave the
sleeves. With body part labels (:mod:`simgen.body.parts`: one bit mask of parts per body face,
one home part per cloth vertex, taken from the garment's skinning weights), the closest feature is
taken from the vertex's own part instead whenever the vertex is inside the body at a face that
belongs to another part only, and a face of the own part lies within ``pinch_distance``: cloth
lying on its own part keeps to it and the pressing part passes through it (inside the other
part, where the statistics count it apart as a body self-intersection). Cloth outside the body
collides with whatever surface is closest, whichever part it belongs to (cloth resting on the
deltoid where skinning folds it over the torso at the shoulder must stay on it), and so does
cloth farther than ``pinch_distance`` from its own part (a loose dress hit by a leg). Faces near
the seam between two parts (the shoulder, the hip) belong to both, so cloth sliding across a seam
sees one continuous surface.
"""

import functools
from types import SimpleNamespace

import warp as wp

from simgen.params import ContactParams
from simgen.sim.warp_toolkit import module_name, resolve_outputs, scalar_types

__all__ = ["ContactParams", "ContactFrame", "eval_contact", "update_contact_frame", "contact_funcs",
           "contact_kernels", "part_inputs"]


@functools.cache
def contact_funcs(scalar) -> SimpleNamespace:
    """Warp functions of the body distance for one scalar type.

    closest_point_triangle(p, a, b, c) -> (closest, barycentric weights of a, b, c, interior flag):
      the exact closest point of a triangle (Voronoi regions of its vertices, edges and face).
    body_distance(mesh, x, query_distance) -> (found, d, n, face, u, v): found is 1 if a body face
      lies within query_distance; d [m] the signed distance (< 0 inside); n the outward unit normal
      = grad(d); face, u, v the closest face and the weights of its first two vertices (float32, as
      warp.mesh_eval_position/velocity take them).
    part_distance(mesh, part_masks, part_bit, x, radius) -> as body_distance, over the faces whose
      mask has part_bit within the box x +- radius only (found 0 if none is closer than radius);
      the sign comes from the chosen face's normal.
    body_contact(mesh, part_masks, home, x, query_distance, pinch_distance) -> as body_distance,
      with the rule of the module doc for a vertex of home part ``home`` (-1: none, plain
      body_distance), plus a last value ``own``: 1 where the own part's surface was taken.
    held_contact(mesh, part_masks, home, x, query_distance, pinch_distance, own) -> as
      body_distance, with the rule's choice given: own = 1 takes the own part's surface within
      pinch_distance (found 0 beyond), 0 the closest surface of the whole body.
    """
    vec3 = scalar_types(scalar).vec3
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
    def body_distance(mesh: wp.uint64, x: vec3, query_distance: float):
        # The float32 BVH query only picks the closest face (and the sign); the distance is then
        # recomputed exactly on that face in the kernel's scalar type.
        q = wp.mesh_query_point_sign_normal(mesh, wp.vec3(x), query_distance)
        if not q.result:
            return 0, zero, vec3(), -1, float(0.0), float(0.0)
        p0 = vec3(wp.mesh_get_point(mesh, q.face * 3 + 0))
        p1 = vec3(wp.mesh_get_point(mesh, q.face * 3 + 1))
        p2 = vec3(wp.mesh_get_point(mesh, q.face * 3 + 2))
        nf = wp.normalize(wp.cross(p1 - p0, p2 - p0))
        c, bary, interior = closest_point_triangle(x, p0, p1, p2)
        u = float(bary[0])
        v = float(bary[1])
        if interior != 0:
            # Closest point inside the face: d is the (linear) plane distance, n the face normal.
            return 1, wp.dot(x - p0, nf), nf, q.face, u, v
        diff = x - c
        dist = wp.length(diff)
        s = one
        if q.sign < 0.0:
            s = -one
        if dist > tiny:
            return 1, s * dist, (s / dist) * diff, q.face, u, v
        return 1, zero, nf, q.face, u, v

    @wp.func
    def part_distance(mesh: wp.uint64, part_masks: wp.array(dtype=wp.int32), part_bit: int, x: vec3,
                      radius: float):
        xf = wp.vec3(x)
        query = wp.mesh_query_aabb(mesh, xf - wp.vec3(radius), xf + wp.vec3(radius))
        f = int(0)
        best_face = int(-1)
        best = scalar(radius)
        best_point = vec3()
        best_bary = vec3()
        best_interior = int(0)
        while wp.mesh_query_aabb_next(query, f):
            if (part_masks[f] & part_bit) != 0:
                c, bary, interior = closest_point_triangle(
                    x, vec3(wp.mesh_get_point(mesh, f * 3 + 0)), vec3(wp.mesh_get_point(mesh, f * 3 + 1)),
                    vec3(wp.mesh_get_point(mesh, f * 3 + 2)))
                dist = wp.length(x - c)
                if dist < best:
                    best = dist
                    best_face = f
                    best_point = c
                    best_bary = bary
                    best_interior = interior
        if best_face < 0:
            return 0, zero, vec3(), -1, float(0.0), float(0.0)
        p0 = vec3(wp.mesh_get_point(mesh, best_face * 3 + 0))
        p1 = vec3(wp.mesh_get_point(mesh, best_face * 3 + 1))
        p2 = vec3(wp.mesh_get_point(mesh, best_face * 3 + 2))
        nf = wp.normalize(wp.cross(p1 - p0, p2 - p0))
        u = float(best_bary[0])
        v = float(best_bary[1])
        if best_interior != 0:
            return 1, wp.dot(x - p0, nf), nf, best_face, u, v
        diff = x - best_point
        s = one
        if wp.dot(diff, nf) < zero:
            s = -one
        if best > tiny:
            return 1, s * best, (s / best) * diff, best_face, u, v
        return 1, zero, nf, best_face, u, v

    @wp.func
    def body_contact(mesh: wp.uint64, part_masks: wp.array(dtype=wp.int32), home: int, x: vec3,
                     query_distance: float, pinch_distance: float):
        found, d, n, face, u, v = body_distance(mesh, x, query_distance)
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
        f0, d0, n0, face0, u0, v0 = body_distance(mesh, x, query_distance)
        return f0, d0, n0, face0, u0, v0

    return SimpleNamespace(closest_point_triangle=closest_point_triangle, body_distance=body_distance,
                           part_distance=part_distance, body_contact=body_contact, held_contact=held_contact)


@functools.cache
def contact_kernels(scalar) -> SimpleNamespace:
    """Kernels for one scalar type: ``.contact`` (energy/gradient/Hessian) and ``.frame``
    (per-vertex closest-point data), one thread per vertex."""
    T = scalar_types(scalar)
    vec3, mat33 = T.vec3, T.mat33
    funcs = contact_funcs(scalar)
    body_contact, held_contact = funcs.body_contact, funcs.held_contact

    @wp.kernel(enable_backward=False, module=module_name(__name__, scalar))
    def contact(
        x: wp.array(dtype=vec3),
        vertex_instance: wp.array(dtype=wp.int32),
        body_meshes: wp.array(dtype=wp.uint64),
        diag_slots: wp.array(dtype=wp.int32),
        margin: scalar,
        stiffness: scalar,
        power: scalar,
        query_distance: float,
        vertex_part: wp.array(dtype=wp.int32),
        part_masks: wp.array(dtype=wp.int32),
        use_parts: int,
        pinch_distance: float,
        part_choice: wp.array(dtype=wp.int32),
        choice_mode: int,
        want_energy: int,
        want_grad: int,
        want_hess: int,
        energy: wp.array(dtype=scalar),
        grad: wp.array(dtype=vec3),
        hess: wp.array(dtype=mat33),
    ):
        i = wp.tid()
        inst = vertex_instance[i]
        mesh = body_meshes[inst]
        if mesh == wp.uint64(0):
            return
        home = int(-1)
        if use_parts != 0:
            home = vertex_part[i]
        found = int(0)
        d = scalar(0.0)
        n = vec3()
        face = int(-1)
        u = float(0.0)
        v = float(0.0)
        if choice_mode == 2:
            # The part rule's choice made at the step's start, held so E stays smooth within the step.
            found, d, n, face, u, v = held_contact(mesh, part_masks, home, x[i], query_distance, pinch_distance,
                                                   part_choice[i])
        else:
            own = int(0)
            found, d, n, face, u, v, own = body_contact(mesh, part_masks, home, x[i], query_distance,
                                                        pinch_distance)
            if choice_mode == 1:
                part_choice[i] = own
        if found == 0 or d >= margin:
            return
        pen = margin - d
        if want_energy != 0:
            wp.atomic_add(energy, inst, stiffness * wp.pow(pen, power))
        if want_grad != 0:
            wp.atomic_add(grad, i, (-stiffness * power * wp.pow(pen, power - scalar(1.0))) * n)
        if want_hess != 0:
            c = stiffness * power * (power - scalar(1.0)) * wp.pow(pen, power - scalar(2.0))
            wp.atomic_add(hess, diag_slots[i], c * wp.outer(n, n))

    @wp.kernel(enable_backward=False, module=module_name(__name__, scalar))
    def frame(
        x: wp.array(dtype=vec3),
        vertex_instance: wp.array(dtype=wp.int32),
        body_meshes: wp.array(dtype=wp.uint64),
        margin: scalar,
        stiffness: scalar,
        power: scalar,
        query_distance: float,
        vertex_part: wp.array(dtype=wp.int32),
        part_masks: wp.array(dtype=wp.int32),
        use_parts: int,
        pinch_distance: float,
        distance: wp.array(dtype=scalar),
        normal: wp.array(dtype=vec3),
        face: wp.array(dtype=wp.int32),
        bary: wp.array(dtype=wp.vec2),
        force: wp.array(dtype=scalar),
    ):
        i = wp.tid()
        distance[i] = scalar(query_distance)
        normal[i] = vec3()
        face[i] = -1
        bary[i] = wp.vec2()
        force[i] = scalar(0.0)
        mesh = body_meshes[vertex_instance[i]]
        if mesh == wp.uint64(0):
            return
        home = int(-1)
        if use_parts != 0:
            home = vertex_part[i]
        found, d, n, f, u, v, own = body_contact(mesh, part_masks, home, x[i], query_distance, pinch_distance)
        if found == 0:
            return
        distance[i] = d
        normal[i] = n
        face[i] = f
        bary[i] = wp.vec2(u, v)
        if d < margin:
            force[i] = stiffness * power * wp.pow(margin - d, power - scalar(1.0))

    return SimpleNamespace(contact=contact, frame=frame)


def part_inputs(model, part_masks, pinch_distance: float) -> list:
    """Kernel arguments (vertex_part, part_masks, use_parts, pinch_distance [m]) of the part rule: on
    when the body has part masks and the model's vertices have home parts (module doc)."""
    use = int(part_masks is not None and model.has_body_parts)
    return [model.vertex_body_part, part_masks if use else None, use, float(pinch_distance)]


def eval_contact(model, positions, body_meshes, params: ContactParams = ContactParams(), *, part_masks=None,
                 part_choice=None, decide_parts: bool = True, energy=None, gradient=None, hessian=None,
                 scale: float = 1.0) -> None:
    """Accumulate the body contact penalty of every vertex.

    positions [m], (V,) vec3; body_meshes: (num_instances,) uint64 warp array of warp.Mesh ids
    (0 = none; each mesh watertight, triangles counter-clockwise seen from outside); part_masks:
    optional (Fb,) int32 body part bit masks per face (:attr:`BodyCollider.part_masks`), which
    switch on the part rule of the module doc for models with home parts; part_choice: optional
    (V,) int32 array holding the rule's choice per vertex: decide_parts=True makes the choice at
    ``positions`` and stores it, False reuses the stored one (a solver step decides at its start
    and holds the choice, so the energy it minimises has no jumps). Outputs (added to,
    optional): energy [J] per instance; gradient [J/m] (V,) vec3; hessian (diagonal blocks, PSD):
    the model's BsrMatrix or its values. scale multiplies all three.
    """
    we, wg, wh, e, g, h = resolve_outputs(energy, gradient, hessian)
    if not (we or wg or wh):
        return
    wp.launch(contact_kernels(model.scalar).contact, dim=model.num_vertices, device=model.device, inputs=[
        positions, model.vertex_instance, body_meshes, model.diag_slots, params.margin, params.stiffness * scale,
        params.power, params.query_distance, *part_inputs(model, part_masks, params.pinch_distance), part_choice,
        0 if part_choice is None else (1 if decide_parts else 2), we, wg, wh, e, g, h])


class ContactFrame:
    """Per-vertex closest-body-point data at one configuration, (V,) arrays on the model's device.

    distance [m] (scalar; query_distance where no body face is that close), normal (vec3, outward,
    zero where none), face (int32, -1 where none), bary (wp.vec2 float32: weights u, v of the
    face's first two vertices), force [N] (scalar): normal force magnitude k p (margin - d)^(p-1),
    0 outside the margin. Friction uses it as its lagged contact set (:mod:`.friction`).
    """

    def __init__(self, model) -> None:
        T = scalar_types(model.scalar)
        n, dev = model.num_vertices, model.device
        self.distance = wp.zeros(n, dtype=T.scalar, device=dev)
        self.normal = wp.zeros(n, dtype=T.vec3, device=dev)
        self.face = wp.full(n, -1, dtype=wp.int32, device=dev)
        self.bary = wp.zeros(n, dtype=wp.vec2, device=dev)
        self.force = wp.zeros(n, dtype=T.scalar, device=dev)


def update_contact_frame(model, positions, body_meshes, params: ContactParams, frame: ContactFrame, *,
                         part_masks=None) -> None:
    """Fill ``frame`` from the closest body points of ``positions`` [m], (V,) vec3 (overwrites);
    part_masks as in :func:`eval_contact`."""
    wp.launch(contact_kernels(model.scalar).frame, dim=model.num_vertices, device=model.device, inputs=[
        positions, model.vertex_instance, body_meshes, params.margin, params.stiffness, params.power,
        params.query_distance, *part_inputs(model, part_masks, params.pinch_distance), frame.distance, frame.normal, frame.face,
        frame.bary, frame.force])
