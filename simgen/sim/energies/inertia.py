"""Inertia term of backward Euler as minimisation (SNUG eqs. 5.4 and 5.6).

    E = 1 / (2 h^2) (x - x_hat)^T M (x - x_hat),   x_hat = x_t + h v_t (+ any explicit forces),

with the lumped (diagonal) mass M: gradient M (x - x_hat) / h^2, Hessian M / h^2 (3x3 diagonal
blocks m_v / h^2 I), added at the diagonal slots.
"""

import functools
from types import SimpleNamespace

import warp as wp

from simgen.errors import InputError
from simgen.sim.warp_toolkit import launch_blocked, module_name, reduce_funcs, resolve_outputs, scalar_types

__all__ = ["eval_inertia", "inertia_kernels"]


@functools.cache
def inertia_kernels(scalar) -> SimpleNamespace:
    """The inertia kernel for one scalar type (``.inertia``, one thread per vertex, launched in
    blocks: the energy is a block reduction per instance)."""
    T = scalar_types(scalar)
    vec3, mat33 = T.vec3, T.mat33
    block_add = reduce_funcs(scalar).block_add

    @wp.kernel(enable_backward=False, module=module_name(__name__, scalar))
    def inertia(
        x: wp.array(dtype=vec3),
        x_hat: wp.array(dtype=vec3),
        mass: wp.array(dtype=scalar),
        vertex_instance: wp.array(dtype=wp.int32),
        step_divisor: wp.array(dtype=wp.int32),
        diag_slots: wp.array(dtype=wp.int32),
        inv_dt2: scalar,
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
        e = scalar(0.0)
        if i < n:
            f = scalar(step_divisor[vertex_instance[i]])
            k = mass[i] * (inv_dt2 * f * f)
            d = x[i] - x_hat[i]
            e = scalar(0.5) * k * wp.dot(d, d)
            if want_grad != 0:
                wp.atomic_add(grad, i, k * d)
            if want_hess != 0:
                wp.atomic_add(hess, diag_slots[i], k * wp.identity(n=3, dtype=scalar))
        if want_energy != 0:  # uniform over the launch, so every thread of a block reaches the tile sum
            block_add(energy, vertex_instance, block, lane, i, n, e)

    return SimpleNamespace(inertia=inertia)


def eval_inertia(model, positions, predicted, dt: float, *, energy=None, gradient=None, hessian=None,
                 scale: float = 1.0) -> None:
    """Accumulate the inertia term.

    positions [m], predicted (x_hat) [m]: (V,) vec3; dt [s]: the step h. Outputs (added to,
    optional): energy [J] per instance; gradient [J/m] (V,) vec3; hessian (diagonal blocks m/h^2 I):
    the model's BsrMatrix or its values. scale multiplies all three.
    """
    if not dt > 0:
        raise InputError(f"time step must be > 0, got {dt!r}")
    we, wg, wh, e, g, h = resolve_outputs(energy, gradient, hessian)
    if not (we or wg or wh):
        return
    launch_blocked(inertia_kernels(model.scalar).inertia, model.num_vertices, model.device, [
        positions, predicted, model.vertex_mass, model.vertex_instance, model.instance_step_divisor, model.diag_slots,
        scale / (dt * dt),
        we, wg, wh, e, g, h])
