"""Dihedral bending energy (SNUG eq. 5.10), its gradient and Gauss-Newton Hessian.

Per hinge e (edge x0-x1, wings x2 and x3, see :func:`simgen.topology.extract_hinges`):

    E_e = k_e (theta - theta_rest)^2 / 2,   k_e = k_bend * l^2 / (4 (a1 + a2))   [J],

theta the signed angle between the face normals N_A = (x1 - x0) x (x2 - x0) and
N_B = (x3 - x0) x (x1 - x0) about the edge (0 when flat, in (-pi, pi]); theta_rest is the
template's angle or 0 ("flat", as SNUG). The difference is wrapped into (-pi, pi].

Gradient of theta (exact): with l = |x1 - x0|, grad_2 = -l N_A / |N_A|^2, grad_3 = -l N_B / |N_B|^2,
and for the edge vertices, with s_A, s_B the positions of the wings' feet along the edge as a
fraction of l, grad_0 = -(1 - s_A) grad_2 - (1 - s_B) grad_3, grad_1 = -s_A grad_2 - s_B grad_3
(translation and rotation invariance).

Hessian: the Gauss-Newton form k_e grad(theta) grad(theta)^T (12x12, rank 1, PSD). It drops
k_e (theta - theta_rest) d2(theta)/dx2, which vanishes at the rest angle and is indefinite away
from it; cloth bending is soft next to the membrane and the mass term, so Newton keeps converging
with the PSD part alone, at the cost of one outer product per hinge.
"""

import functools
import math
from types import SimpleNamespace

import warp as wp

from simgen.sim.warp_toolkit import launch_blocked, module_name, reduce_funcs, resolve_outputs, scalar_types

__all__ = ["eval_bending", "bending_funcs", "bending_kernels"]


@functools.cache
def bending_funcs(scalar) -> SimpleNamespace:
    """Warp functions of the dihedral angle for one scalar type (shared with the damping term).

    dihedral_angle(x0, x1, x2, x3) -> theta; dihedral_angle_grad(x0, x1, x2, x3) -> (theta, g0, g1,
    g2, g3) (all zero on a degenerate hinge); wrap_angle(a) -> a in (-pi, pi];
    add_hinge_gradient(grad, hinges, e, c, g0..g3) adds c * g_k; add_hinge_gn_hessian(hess, slots, e,
    c, g0..g3) adds c * g_a g_b^T.
    """
    T = scalar_types(scalar)
    vec3, mat33 = T.vec3, T.mat33
    zero = scalar(0.0)
    pi = scalar(math.pi)
    two_pi = scalar(2.0 * math.pi)
    # Below this squared normal length (relative to l^4) a wing is degenerate: no angle, no force.
    degenerate = scalar(1.0e-24 if scalar is wp.float64 else 1.0e-12)

    @wp.func
    def dihedral_angle(x0: vec3, x1: vec3, x2: vec3, x3: vec3):
        e = x1 - x0
        na = wp.cross(e, x2 - x0)
        nb = wp.cross(x3 - x0, e)
        l = wp.length(e)
        if l <= zero:
            return zero
        return wp.atan2(wp.dot(wp.cross(na, nb), e) / l, wp.dot(na, nb))

    @wp.func
    def dihedral_angle_grad(x0: vec3, x1: vec3, x2: vec3, x3: vec3):
        e = x1 - x0
        na = wp.cross(e, x2 - x0)
        nb = wp.cross(x3 - x0, e)
        l2 = wp.dot(e, e)
        na2 = wp.dot(na, na)
        nb2 = wp.dot(nb, nb)
        z = vec3()
        if na2 <= degenerate * l2 * l2 or nb2 <= degenerate * l2 * l2:
            return zero, z, z, z, z
        l = wp.sqrt(l2)
        theta = wp.atan2(wp.dot(wp.cross(na, nb), e) / l, wp.dot(na, nb))
        g2 = (-l / na2) * na
        g3 = (-l / nb2) * nb
        sa = wp.dot(x2 - x0, e) / l2
        sb = wp.dot(x3 - x0, e) / l2
        g0 = -(scalar(1.0) - sa) * g2 - (scalar(1.0) - sb) * g3
        g1 = -sa * g2 - sb * g3
        return theta, g0, g1, g2, g3

    @wp.func
    def wrap_angle(a: scalar):
        if a > pi:
            return a - two_pi
        if a <= -pi:
            return a + two_pi
        return a

    @wp.func
    def add_hinge_gradient(grad: wp.array(dtype=vec3), hinges: wp.array2d(dtype=wp.int32), e: int, c: scalar,
                           g0: vec3, g1: vec3, g2: vec3, g3: vec3):
        wp.atomic_add(grad, hinges[e, 0], c * g0)
        wp.atomic_add(grad, hinges[e, 1], c * g1)
        wp.atomic_add(grad, hinges[e, 2], c * g2)
        wp.atomic_add(grad, hinges[e, 3], c * g3)

    @wp.func
    def add_hinge_gn_hessian(hess: wp.array(dtype=mat33), slots: wp.array2d(dtype=wp.int32), e: int, c: scalar,
                             g0: vec3, g1: vec3, g2: vec3, g3: vec3):
        for a in range(4):
            ga = g0
            if a == 1:
                ga = g1
            elif a == 2:
                ga = g2
            elif a == 3:
                ga = g3
            cga = c * ga
            wp.atomic_add(hess, slots[e, 4 * a + 0], wp.outer(cga, g0))
            wp.atomic_add(hess, slots[e, 4 * a + 1], wp.outer(cga, g1))
            wp.atomic_add(hess, slots[e, 4 * a + 2], wp.outer(cga, g2))
            wp.atomic_add(hess, slots[e, 4 * a + 3], wp.outer(cga, g3))

    return SimpleNamespace(dihedral_angle=dihedral_angle, dihedral_angle_grad=dihedral_angle_grad,
                           wrap_angle=wrap_angle, add_hinge_gradient=add_hinge_gradient,
                           add_hinge_gn_hessian=add_hinge_gn_hessian)


@functools.cache
def bending_kernels(scalar) -> SimpleNamespace:
    """The bending kernel for one scalar type (``.bending``, one thread per hinge, launched in
    blocks: the energy is a block reduction per instance)."""
    T = scalar_types(scalar)
    vec3, mat33 = T.vec3, T.mat33
    fn = bending_funcs(scalar)
    block_add = reduce_funcs(scalar).block_add

    @wp.kernel(enable_backward=False, module=module_name(__name__, scalar))
    def bending(
        x: wp.array(dtype=vec3),
        hinges: wp.array2d(dtype=wp.int32),
        stiffness: wp.array(dtype=scalar),
        rest_angle: wp.array(dtype=scalar),
        hinge_instance: wp.array(dtype=wp.int32),
        instance_active: wp.array(dtype=wp.int32),
        hinge_slots: wp.array2d(dtype=wp.int32),
        scale: scalar,
        want_energy: int,
        want_grad: int,
        want_hess: int,
        energy: wp.array(dtype=scalar),
        grad: wp.array(dtype=vec3),
        hess: wp.array(dtype=mat33),
        n: int,
    ):
        block, lane = wp.tid()
        e = block * wp.block_dim() + lane
        value = scalar(0.0)
        live = False
        if e < n:
            live = instance_active[hinge_instance[e]] != 0
        if live:
            theta, g0, g1, g2, g3 = fn.dihedral_angle_grad(
                x[hinges[e, 0]], x[hinges[e, 1]], x[hinges[e, 2]], x[hinges[e, 3]])
            k = stiffness[e] * scale
            delta = fn.wrap_angle(theta - rest_angle[e])
            value = scalar(0.5) * k * delta * delta
            if want_grad != 0:
                fn.add_hinge_gradient(grad, hinges, e, k * delta, g0, g1, g2, g3)
            if want_hess != 0:
                fn.add_hinge_gn_hessian(hess, hinge_slots, e, k, g0, g1, g2, g3)
        if want_energy != 0:  # uniform over the launch, so every thread of a block reaches the tile sum
            block_add(energy, hinge_instance, block, lane, e, n, value)

    return SimpleNamespace(bending=bending)


def eval_bending(model, positions, *, energy=None, gradient=None, hessian=None, scale: float = 1.0) -> None:
    """Accumulate the dihedral bending energy of every hinge of ``model``.

    positions [m], (V,) vec3. Outputs (added to, optional): energy [J] per instance
    (num_instances,); gradient [J/m] (V,) vec3; hessian (Gauss-Newton, PSD): the model's BsrMatrix or
    its values. scale multiplies all three.
    """
    we, wg, wh, e, g, h = resolve_outputs(energy, gradient, hessian)
    if model.num_hinges == 0 or not (we or wg or wh):
        return
    k = bending_kernels(model.scalar).bending
    launch_blocked(k, model.num_hinges, model.device, [
        positions, model.hinges, model.hinge_stiffness, model.hinge_rest_angle, model.hinge_instance,
        model.instance_active, model.hinge_slots, scale, we, wg, wh, e, g, h])
