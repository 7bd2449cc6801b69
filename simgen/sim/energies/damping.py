"""Damping as an incremental dissipation potential (Rayleigh damping, rigid-motion free).

Added to the backward-Euler objective over one step of length h from x_t (the step's start):

    D = beta / h * [ sum_t A_t Psi_StVK(G(x) - G(x_t)) + sum_e k_e (theta_e(x) - theta_e(x_t))^2 / 2 ]
      + alpha / (2 h) * (x - x_t)^T M (x - x_t),

with the membrane's Psi (lambda h, mu h) and the bending stiffness k_e of the same elements,
beta [s] = Material.damping_stiffness (per triangle / hinge), alpha [1/s] =
Material.damping_mass (per vertex). Its gradient is a viscous force: for small steps,
G(x) - G(x_t) ~ dG/dx (x - x_t), so the first part is beta/(2h) (x - x_t)^T K (x - x_t) with K
the elastic stiffness, and -grad D = -(alpha M + beta K) v: Rayleigh damping. Unlike the classic
linearised form it is a function of the strain and angle rates only, so rigid rotations are not
damped, and it is an exact potential (the minimisation stays a minimisation, finite differences
check it).

Hessians: the membrane part is StVK's with the stress of the strain increment,
S = lambda tr(dG) I + 2 mu dG, projected to PSD as the membrane's; the bending part is
Gauss-Newton (beta/h) k_e grad(theta) grad(theta)^T; the mass part is alpha m / h I.
"""

import functools
from types import SimpleNamespace

import warp as wp

from simgen.errors import InputError
from simgen.sim.warp_toolkit import (launch_blocked, math_funcs, module_name, reduce_funcs, resolve_outputs,
                                         scalar_types)
from simgen.sim.energies.bending import bending_funcs
from simgen.sim.energies.membrane import membrane_funcs

__all__ = ["eval_damping", "damping_kernels"]


@functools.cache
def damping_kernels(scalar) -> SimpleNamespace:
    """Kernels for one scalar type: ``.membrane`` (per triangle), ``.bending`` (per hinge),
    ``.mass`` (per vertex), each launched in blocks (the energy is a block reduction per instance)."""
    T = scalar_types(scalar)
    vec3, mat22, mat33 = T.vec3, T.mat22, T.mat33
    mf = membrane_funcs(scalar)
    bf = bending_funcs(scalar)
    project_psd6 = math_funcs(scalar).project_psd6
    block_add = reduce_funcs(scalar).block_add
    zero = scalar(0.0)
    mod = module_name(__name__, scalar)

    @wp.kernel(enable_backward=False, module=mod)
    def membrane(
        x: wp.array(dtype=vec3),
        x_start: wp.array(dtype=vec3),
        tris: wp.array2d(dtype=wp.int32),
        inv_rest: wp.array(dtype=mat22),
        rest_area: wp.array(dtype=scalar),
        lam: wp.array(dtype=scalar),
        mu: wp.array(dtype=scalar),
        beta: wp.array(dtype=scalar),
        tri_instance: wp.array(dtype=wp.int32),
        tri_slots: wp.array2d(dtype=wp.int32),
        step_divisor: wp.array(dtype=wp.int32),
        inv_dt: scalar,
        scale: scalar,
        project: int,
        want_energy: int,
        want_grad: int,
        want_hess: int,
        energy: wp.array(dtype=scalar),
        grad: wp.array(dtype=vec3),
        hess: wp.array(dtype=mat33),
        n: int,
    ):
        block, lane = wp.tid()
        t = block * wp.block_dim() + lane
        e = zero
        c = zero
        if t < n:
            c = beta[t] * (inv_dt * scalar(step_divisor[tri_instance[t]])) * rest_area[t] * scale
        if c > zero:
            i0 = tris[t, 0]
            i1 = tris[t, 1]
            i2 = tris[t, 2]
            dm_inv = inv_rest[t]
            f = mf.deformation_gradient(x[i0], x[i1], x[i2], dm_inv)
            f_start = mf.deformation_gradient(x_start[i0], x_start[i1], x_start[i2], dm_inv)
            dg = mf.green_strain(f) - mf.green_strain(f_start)
            e = c * mf.stvk_density(dg, lam[t], mu[t])
            if want_grad != 0 or want_hess != 0:
                s = mf.stvk_stress(dg, lam[t], mu[t])
                if want_grad != 0:
                    mf.add_triangle_gradient(grad, i0, i1, i2, f * s, dm_inv, c)
                if want_hess != 0:
                    h = mf.stvk_hessian(f, s, lam[t], mu[t])
                    if project != 0 and not mf.s_is_psd(s):
                        h = project_psd6(h)
                    mf.add_triangle_hessian(hess, tri_slots, t, h, dm_inv, c)
        if want_energy != 0:  # uniform over the launch, so every thread of a block reaches the tile sum
            block_add(energy, tri_instance, block, lane, t, n, e)

    @wp.kernel(enable_backward=False, module=mod)
    def bending(
        x: wp.array(dtype=vec3),
        x_start: wp.array(dtype=vec3),
        hinges: wp.array2d(dtype=wp.int32),
        stiffness: wp.array(dtype=scalar),
        beta: wp.array(dtype=scalar),
        hinge_instance: wp.array(dtype=wp.int32),
        hinge_slots: wp.array2d(dtype=wp.int32),
        step_divisor: wp.array(dtype=wp.int32),
        inv_dt: scalar,
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
        value = zero
        k = zero
        if e < n:
            k = beta[e] * (inv_dt * scalar(step_divisor[hinge_instance[e]])) * stiffness[e] * scale
        if k > zero:
            j0 = hinges[e, 0]
            j1 = hinges[e, 1]
            j2 = hinges[e, 2]
            j3 = hinges[e, 3]
            theta, g0, g1, g2, g3 = bf.dihedral_angle_grad(x[j0], x[j1], x[j2], x[j3])
            theta_start = bf.dihedral_angle(x_start[j0], x_start[j1], x_start[j2], x_start[j3])
            delta = bf.wrap_angle(theta - theta_start)
            value = scalar(0.5) * k * delta * delta
            if want_grad != 0:
                bf.add_hinge_gradient(grad, hinges, e, k * delta, g0, g1, g2, g3)
            if want_hess != 0:
                bf.add_hinge_gn_hessian(hess, hinge_slots, e, k, g0, g1, g2, g3)
        if want_energy != 0:  # uniform over the launch, so every thread of a block reaches the tile sum
            block_add(energy, hinge_instance, block, lane, e, n, value)

    @wp.kernel(enable_backward=False, module=mod)
    def mass(
        x: wp.array(dtype=vec3),
        x_start: wp.array(dtype=vec3),
        vertex_mass: wp.array(dtype=scalar),
        alpha: wp.array(dtype=scalar),
        vertex_instance: wp.array(dtype=wp.int32),
        diag_slots: wp.array(dtype=wp.int32),
        step_divisor: wp.array(dtype=wp.int32),
        inv_dt: scalar,
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
        i = block * wp.block_dim() + lane
        e = zero
        k = zero
        if i < n:
            k = alpha[i] * vertex_mass[i] * (inv_dt * scalar(step_divisor[vertex_instance[i]])) * scale
        if k > zero:
            d = x[i] - x_start[i]
            e = scalar(0.5) * k * wp.dot(d, d)
            if want_grad != 0:
                wp.atomic_add(grad, i, k * d)
            if want_hess != 0:
                wp.atomic_add(hess, diag_slots[i], k * wp.identity(n=3, dtype=scalar))
        if want_energy != 0:  # uniform over the launch, so every thread of a block reaches the tile sum
            block_add(energy, vertex_instance, block, lane, i, n, e)

    return SimpleNamespace(membrane=membrane, bending=bending, mass=mass)


def eval_damping(model, positions, start_positions, dt: float, *, energy=None, gradient=None, hessian=None,
                 scale: float = 1.0, project: bool = True) -> None:
    """Accumulate the damping dissipation potential (membrane, bending and mass parts).

    positions [m], start_positions (x_t) [m]: (V,) vec3; dt [s]: the step h. Elements whose
    material has zero damping cost a thread each and add nothing. Outputs (added to, optional):
    energy [J] per instance; gradient [J/m] (V,) vec3; hessian (PSD): the model's BsrMatrix or
    its values. scale multiplies all three; project=False keeps the exact membrane Hessian.
    """
    if not dt > 0:
        raise InputError(f"time step must be > 0, got {dt!r}")
    we, wg, wh, e, g, h = resolve_outputs(energy, gradient, hessian)
    if not (we or wg or wh):
        return
    k = damping_kernels(model.scalar)
    inv_dt = 1.0 / dt
    dev = model.device
    if model.num_triangles:
        launch_blocked(k.membrane, model.num_triangles, dev, [
            positions, start_positions, model.triangles, model.tri_inv_rest, model.tri_rest_area, model.tri_lambda,
            model.tri_mu, model.tri_damping, model.tri_instance, model.tri_slots, model.instance_step_divisor, inv_dt,
            scale, int(project), we, wg, wh, e, g, h])
    if model.num_hinges:
        launch_blocked(k.bending, model.num_hinges, dev, [
            positions, start_positions, model.hinges, model.hinge_stiffness, model.hinge_damping,
            model.hinge_instance, model.hinge_slots, model.instance_step_divisor, inv_dt, scale, we, wg, wh, e, g, h])
    launch_blocked(k.mass, model.num_vertices, dev, [
        positions, start_positions, model.vertex_mass, model.vertex_damping_mass, model.vertex_instance,
        model.diag_slots, model.instance_step_divisor, inv_dt, scale, we, wg, wh, e, g, h])
