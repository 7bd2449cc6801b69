"""Gravity potential (SNUG eq. 5.11): E = -sum_v m_v g . x_v, gradient -m_v g, zero Hessian."""

import functools
from types import SimpleNamespace

import warp as wp

from simgen.params import GravityParams
from simgen.sim.warp_toolkit import launch_blocked, module_name, reduce_funcs, resolve_outputs, scalar_types

__all__ = ["GravityParams", "eval_gravity", "gravity_kernels"]


@functools.cache
def gravity_kernels(scalar) -> SimpleNamespace:
    """The gravity kernel for one scalar type (``.gravity``, one thread per vertex, launched in
    blocks: the energy is a block reduction per instance)."""
    vec3 = scalar_types(scalar).vec3
    block_add = reduce_funcs(scalar).block_add

    @wp.kernel(enable_backward=False, module=module_name(__name__, scalar))
    def gravity(
        x: wp.array(dtype=vec3),
        mass: wp.array(dtype=scalar),
        vertex_instance: wp.array(dtype=wp.int32),
        g: vec3,
        scale: scalar,
        want_energy: int,
        want_grad: int,
        energy: wp.array(dtype=scalar),
        grad: wp.array(dtype=vec3),
        n: int,
    ):
        block, lane = wp.tid()
        i = block * wp.block_dim() + lane
        e = scalar(0.0)
        if i < n:
            m = mass[i] * scale
            e = -m * wp.dot(g, x[i])
            if want_grad != 0:
                wp.atomic_add(grad, i, -m * g)
        if want_energy != 0:  # uniform over the launch, so every thread of a block reaches the tile sum
            block_add(energy, vertex_instance, block, lane, i, n, e)

    return SimpleNamespace(gravity=gravity)


def eval_gravity(model, positions, params: GravityParams = GravityParams(), *, energy=None, gradient=None,
                 hessian=None, scale: float = 1.0) -> None:
    """Accumulate the gravity potential of every vertex.

    positions [m], (V,) vec3. Outputs (added to, optional): energy [J] per instance; gradient [J/m]
    (V,) vec3. The Hessian is zero: a hessian argument is accepted and left untouched.
    """
    we, wg, _, e, g, _ = resolve_outputs(energy, gradient, hessian)
    if not (we or wg):
        return
    vec3 = scalar_types(model.scalar).vec3
    launch_blocked(gravity_kernels(model.scalar).gravity, model.num_vertices, model.device, [
        positions, model.vertex_mass, model.vertex_instance, vec3(*params.gravity), scale, we, wg, e, g])
