"""Lagged Coulomb friction against the body as a smoothed dissipation potential (IPC-style).

For every cloth vertex in contact in the lagged :class:`~simgen.sim.energies.contact.ContactFrame`
(normal force lambda [N] > 0, capped at ``max_normal_load`` times the vertex weight, outward normal n, closest body face and barycentrics, all frozen at
the configuration where the frame was taken, typically the start of the step or the previous
Newton iterate):

    u = (I - n n^T) (x - x_t - h v_body),        y = |u|   (tangential slip over the step [m]),
    D = mu * lambda * f0(y),

with v_body the body's velocity at the lagged contact point (``warp.mesh_eval_velocity`` of the
instance's body mesh: build it with ``velocities`` = the body's vertex velocities over the step;
a mesh without velocities is a static body), mu the vertex's material friction coefficient, and
IPC's (Li et al. 2020) mollifier with eps = eps_v h:

    f0(y) = y                                   for y >= eps   (sliding: force mu lambda, opposing slip)
    f0(y) = -y^3 / (3 eps^2) + y^2 / eps + eps / 3   for y < eps   (sticking, smoothed: C1 at 0 and eps)

Gradient mu lambda f1(y) / y u with f1 = f0'; Hessian mu lambda [f1/y (I - n n^T) + (f1' y - f1) / y^3
u u^T], which is PSD in both regimes (along u: 2/eps - 2y/eps^2 >= 0 while sticking, 0 while
sliding; across: f1/y > 0), so no projection is needed. The lagging (n, lambda and the contact
point fixed) makes this an exact potential during one minimisation.
"""

import functools
from types import SimpleNamespace

import warp as wp

from simgen.errors import InputError
from simgen.params import FrictionParams
from simgen.sim.warp_toolkit import module_name, resolve_outputs, scalar_types

__all__ = ["FrictionParams", "eval_friction", "friction_kernels"]


@functools.cache
def friction_kernels(scalar) -> SimpleNamespace:
    """The friction kernel for one scalar type (``.friction``, one thread per vertex)."""
    T = scalar_types(scalar)
    vec3, mat33 = T.vec3, T.mat33
    zero = scalar(0.0)
    one = scalar(1.0)

    @wp.kernel(enable_backward=False, module=module_name(__name__, scalar))
    def friction(
        x: wp.array(dtype=vec3),
        x_start: wp.array(dtype=vec3),
        vertex_instance: wp.array(dtype=wp.int32),
        body_meshes: wp.array(dtype=wp.uint64),
        friction_mu: wp.array(dtype=scalar),
        vertex_mass: wp.array(dtype=scalar),
        max_load_accel: scalar,
        diag_slots: wp.array(dtype=wp.int32),
        lag_normal: wp.array(dtype=vec3),
        lag_face: wp.array(dtype=wp.int32),
        lag_bary: wp.array(dtype=wp.vec2),
        lag_force: wp.array(dtype=scalar),
        step_divisor: wp.array(dtype=wp.int32),
        dt: scalar,
        eps_step: scalar,
        scale: scalar,
        want_energy: int,
        want_grad: int,
        want_hess: int,
        energy: wp.array(dtype=scalar),
        grad: wp.array(dtype=vec3),
        hess: wp.array(dtype=mat33),
    ):
        i = wp.tid()
        face = lag_face[i]
        c = friction_mu[i] * wp.min(lag_force[i], max_load_accel * vertex_mass[i]) * scale
        if face < 0 or c <= zero:
            return
        inst = vertex_instance[i]
        mesh = body_meshes[inst]
        if mesh == wp.uint64(0):
            return
        b = lag_bary[i]
        v_body = vec3(wp.mesh_eval_velocity(mesh, face, b[0], b[1]))
        n = lag_normal[i]
        f = scalar(step_divisor[inst])
        eps = eps_step / f  # eps_v h of this instance's step
        disp = x[i] - x_start[i] - (dt / f) * v_body
        u = disp - wp.dot(disp, n) * n
        y = wp.length(u)
        # f0, f1/y and the u u^T coefficient (f1' y - f1) / y^3 of the two regimes.
        f0 = y
        a = zero
        b_uu = zero
        if y >= eps:
            a = one / y
            b_uu = -one / (y * y * y)
        else:
            f0 = -y * y * y / (scalar(3.0) * eps * eps) + y * y / eps + eps / scalar(3.0)
            a = scalar(2.0) / eps - y / (eps * eps)
            if y > zero:
                b_uu = -one / (eps * eps * y)
        if want_energy != 0:
            wp.atomic_add(energy, inst, c * f0)
        if want_grad != 0:
            wp.atomic_add(grad, i, (c * a) * u)
        if want_hess != 0:
            p = wp.identity(n=3, dtype=scalar) - wp.outer(n, n)
            wp.atomic_add(hess, diag_slots[i], c * (a * p + b_uu * wp.outer(u, u)))

    return SimpleNamespace(friction=friction)


def _max_load_accel(params: FrictionParams) -> float:
    # The cap on lambda as an acceleration [m/s^2] times the vertex mass; 1e30 stands for no cap.
    return min(params.max_normal_load * 9.81, 1.0e30)


def eval_friction(model, positions, start_positions, body_meshes, frame, dt: float,
                  params: FrictionParams = FrictionParams(), *, energy=None, gradient=None, hessian=None,
                  scale: float = 1.0) -> None:
    """Accumulate the lagged friction potential of every vertex in contact in ``frame``.

    positions [m] and start_positions (x_t, the step's start) [m]: (V,) vec3; body_meshes:
    (num_instances,) uint64 mesh ids (0 = none) with per-vertex velocities [m/s] over the step;
    frame: a ContactFrame filled by :func:`~simgen.sim.energies.contact.update_contact_frame`;
    dt [s]: the step h. Outputs (added to, optional): energy [J] per instance; gradient [J/m] (V,)
    vec3; hessian (diagonal blocks, PSD): the model's BsrMatrix or its values. scale multiplies all three.
    """
    if not dt > 0:
        raise InputError(f"time step must be > 0, got {dt!r}")
    we, wg, wh, e, g, h = resolve_outputs(energy, gradient, hessian)
    if not (we or wg or wh):
        return
    wp.launch(friction_kernels(model.scalar).friction, dim=model.num_vertices, device=model.device, inputs=[
        positions, start_positions, model.vertex_instance, body_meshes, model.vertex_friction, model.vertex_mass,
        _max_load_accel(params), model.diag_slots,
        frame.normal, frame.face, frame.bary, frame.force, model.instance_step_divisor, dt,
        params.smoothing_velocity * dt, scale,
        we, wg, wh, e, g, h])
