"""The ground plane: the body contact's penalty against the floor y = height, and its projection.

The body stands on the floor (y = 0 for the library's bodies and motions), so cloth must not
sink through it: a dress hem in a deep squat, or a garment that has come off the body, lies on it.
Per cloth vertex with height above the floor d = y - height:

    E_v = k max(margin - d, 0)^p,   grad = -k p (margin - d)^(p-1) e_y,   Hessian = k p (p-1) (margin - d)^(p-2) e_y e_y^T,

with the body contact's margin, stiffness k and power p (:class:`~simgen.sim.energies.contact.ContactParams`):
one contact law for every surface the cloth meets. After each substep :func:`project_floor` puts
any vertex below ``height + offset`` on that level and removes its downward velocity, as the body
projection does for the body. The plane has no friction (a garment on the floor may slide). The
torch losses of :mod:`simgen.physics` have no floor term (SNUG's losses have none), like
``self_contact`` it is the solver's only.
"""

import functools
from types import SimpleNamespace

import warp as wp

from simgen.sim.warp_toolkit import module_name, resolve_outputs, scalar_types

__all__ = ["eval_floor", "project_floor", "floor_kernels"]


@functools.cache
def floor_kernels(scalar) -> SimpleNamespace:
    """Kernels for one scalar type: ``.floor`` (energy/gradient/Hessian) and ``.project``, one
    thread per vertex."""
    T = scalar_types(scalar)
    vec3, mat33 = T.vec3, T.mat33
    zero = scalar(0.0)

    @wp.kernel(enable_backward=False, module=module_name(__name__, scalar))
    def floor(
        x: wp.array(dtype=vec3),
        vertex_instance: wp.array(dtype=wp.int32),
        diag_slots: wp.array(dtype=wp.int32),
        height: scalar,
        margin: scalar,
        stiffness: scalar,
        power: scalar,
        want_energy: int,
        want_grad: int,
        want_hess: int,
        energy: wp.array(dtype=scalar),
        grad: wp.array(dtype=vec3),
        hess: wp.array(dtype=mat33),
    ):
        i = wp.tid()
        pen = margin - (x[i][1] - height)
        if pen <= zero:
            return
        if want_energy != 0:
            wp.atomic_add(energy, vertex_instance[i], stiffness * wp.pow(pen, power))
        if want_grad != 0:
            wp.atomic_add(grad, i, vec3(zero, -stiffness * power * wp.pow(pen, power - scalar(1.0)), zero))
        if want_hess != 0:
            c = stiffness * power * (power - scalar(1.0)) * wp.pow(pen, power - scalar(2.0))
            h = mat33()
            h[1, 1] = c
            wp.atomic_add(hess, diag_slots[i], h)

    @wp.kernel(enable_backward=False, module=module_name(__name__, scalar))
    def project(x: wp.array(dtype=vec3), v: wp.array(dtype=vec3), pinned: wp.array(dtype=wp.int32), level: scalar):
        i = wp.tid()
        xi = x[i]
        if pinned[i] != 0 or xi[1] >= level:
            return
        x[i] = vec3(xi[0], level, xi[2])
        vi = v[i]
        if vi[1] < zero:
            v[i] = vec3(vi[0], zero, vi[2])

    return SimpleNamespace(floor=floor, project=project)


def eval_floor(model, positions, height: float, params, *, energy=None, gradient=None, hessian=None,
               scale: float = 1.0) -> None:
    """Accumulate the floor penalty of every vertex.

    positions [m], (V,) vec3; height [m]: the floor's y; params: a
    :class:`~simgen.sim.energies.contact.ContactParams` (margin, stiffness, power). Outputs (added
    to, optional): energy [J] per instance; gradient [J/m] (V,) vec3; hessian (diagonal blocks,
    PSD): the model's BsrMatrix or its values. scale multiplies all three.
    """
    we, wg, wh, e, g, h = resolve_outputs(energy, gradient, hessian)
    if not (we or wg or wh):
        return
    wp.launch(floor_kernels(model.scalar).floor, dim=model.num_vertices, device=model.device, inputs=[
        positions, model.vertex_instance, model.diag_slots, height, params.margin, params.stiffness * scale,
        params.power, we, wg, wh, e, g, h])


def project_floor(model, state, height: float, offset: float = 0.0) -> None:
    """Move every unpinned vertex of ``state`` below ``height + offset`` [m] up to that level and
    remove its downward velocity (in place)."""
    wp.launch(floor_kernels(model.scalar).project, dim=model.num_vertices, device=model.device,
              inputs=[state.positions, state.velocities, model.vertex_pinned, height + offset])
