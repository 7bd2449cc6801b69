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

Signed distance and normal: the body-surface query of :mod:`simgen.body.surface_query` (its
specification and its Warp functions, :func:`~simgen.body.surface_query.contact_funcs`), with the
pseudo-normal sign (local and cheap: d and n come from the same closest feature, so the energy is
C1 across the surface; no winding-number tree to refit each substep) and, with body part labels,
its body part rule (cloth on its own part keeps to it where another part presses into it). It
needs a watertight, outward-oriented body (the SMPL/anny skin is), and it misclassifies a vertex
that went past the medial axis of a thin limb (> its half thickness, several cm) in one step, which
these step sizes and stiffnesses make unlikely; outputs can still be audited with winding numbers
(:func:`simgen.body.surface.project_to_surface`).

Bodies: one warp.Mesh per instance (bodies of different instances overlap in space), passed as a
(num_instances,) uint64 array of mesh ids indexed by the vertex's instance; id 0 = no body.
"""

import functools
from types import SimpleNamespace

import warp as wp

from simgen.body.surface_query import contact_funcs
from simgen.params import ContactParams
from simgen.sim.warp_toolkit import module_name, resolve_outputs, scalar_types

__all__ = ["ContactParams", "ContactFrame", "eval_contact", "update_contact_frame", "contact_kernels",
           "part_inputs"]


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
