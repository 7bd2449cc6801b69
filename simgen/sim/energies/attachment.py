"""Attachments: cloth vertices tied to points of the moving body surface by springs (a waistband).

Each attached vertex i has a point on its instance's body: a body triangle (p0, p1, p2),
barycentric coordinates b, and an offset o in the triangle's frame (t1 along p1 - p0, n its unit
normal, t2 = n x t1; :func:`simgen.garment.waistband.triangle_frame_coordinates`). The anchor moves
with the posed body, within a step as the collider interpolates it:

    a = b0 p0 + b1 p1 + b2 p2 + o0 t1 + o1 n + o2 t2,
    E_i = k_i / 2 |x_i - a|^2,   grad = k_i (x_i - a),   Hessian = k_i I   (exact: a does not depend on x).

Which vertices and how stiff: :mod:`simgen.garment.waistband`. The torch losses of
:mod:`simgen.physics` have no attachment term (SNUG's have none); it is the solver's only.
"""

import functools
from types import SimpleNamespace

import warp as wp

from simgen.sim.warp_toolkit import module_name, resolve_outputs, scalar_types

__all__ = ["eval_attachment", "attachment_kernels"]


@functools.cache
def attachment_kernels(scalar) -> SimpleNamespace:
    """The attachment kernel for one scalar type (``.attachment``, one thread per attached vertex)."""
    T = scalar_types(scalar)
    vec3, mat33 = T.vec3, T.mat33

    @wp.kernel(enable_backward=False, module=module_name(__name__, scalar))
    def attachment(
        x: wp.array(dtype=vec3),
        vertex_instance: wp.array(dtype=wp.int32),
        body_meshes: wp.array(dtype=wp.uint64),
        diag_slots: wp.array(dtype=wp.int32),
        attach_vertex: wp.array(dtype=wp.int32),
        attach_face: wp.array(dtype=wp.int32),
        attach_bary: wp.array(dtype=vec3),
        attach_offset: wp.array(dtype=vec3),
        attach_stiffness: wp.array(dtype=scalar),
        scale: scalar,
        want_energy: int,
        want_grad: int,
        want_hess: int,
        energy: wp.array(dtype=scalar),
        grad: wp.array(dtype=vec3),
        hess: wp.array(dtype=mat33),
    ):
        a = wp.tid()
        i = attach_vertex[a]
        inst = vertex_instance[i]
        mesh = body_meshes[inst]
        if mesh == wp.uint64(0):
            return
        f = attach_face[a]
        p0 = vec3(wp.mesh_get_point(mesh, f * 3 + 0))
        p1 = vec3(wp.mesh_get_point(mesh, f * 3 + 1))
        p2 = vec3(wp.mesh_get_point(mesh, f * 3 + 2))
        b = attach_bary[a]
        o = attach_offset[a]
        t1 = wp.normalize(p1 - p0)
        n = wp.normalize(wp.cross(p1 - p0, p2 - p0))
        t2 = wp.cross(n, t1)
        anchor = b[0] * p0 + b[1] * p1 + b[2] * p2 + o[0] * t1 + o[1] * n + o[2] * t2
        k = attach_stiffness[a] * scale
        d = x[i] - anchor
        if want_energy != 0:
            wp.atomic_add(energy, inst, scalar(0.5) * k * wp.dot(d, d))
        if want_grad != 0:
            wp.atomic_add(grad, i, k * d)
        if want_hess != 0:
            wp.atomic_add(hess, diag_slots[i], k * wp.identity(n=3, dtype=scalar))

    return SimpleNamespace(attachment=attachment)


def eval_attachment(model, positions, body_meshes, *, energy=None, gradient=None, hessian=None,
                    scale: float = 1.0) -> None:
    """Accumulate the springs of the model's attached vertices (:attr:`ClothModel.attach_vertex`, ...).

    positions [m], (V,) vec3; body_meshes: (num_instances,) uint64 mesh ids of the posed bodies (0 =
    none: that instance's springs are off). Outputs (added to, optional): energy [J] per instance;
    gradient [J/m] (V,) vec3; hessian (diagonal blocks): the model's BsrMatrix or its values. scale
    multiplies all three.
    """
    if model.num_attachments == 0:
        return
    we, wg, wh, e, g, h = resolve_outputs(energy, gradient, hessian)
    if not (we or wg or wh):
        return
    wp.launch(attachment_kernels(model.scalar).attachment, dim=model.num_attachments, device=model.device, inputs=[
        positions, model.vertex_instance, body_meshes, model.diag_slots, model.attach_vertex, model.attach_face,
        model.attach_bary, model.attach_offset, model.attach_stiffness, scale, we, wg, wh, e, g, h])
