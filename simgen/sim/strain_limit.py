"""Isotropic strain limiting: after a solver step, no triangle stretches past 1 + limit.

Backward Euler with a penalty contact can squeeze a single cloth vertex far ahead of its
neighbours in one step: where a fast body part presses cloth against another (the thigh lifting
into the belly at a run, with the T-shirt's hem between them), the converged step moves one hem
vertex 2-3 cm while its neighbours move 1 cm, and that triangle reads 3-10x its rest size for a
frame (measured in BENCHMARKS.md). ARCSim bounds such deformation by strain limiting (Wang,
O'Brien and Ramamoorthi 2010, "Multi-resolution isotropic strain limiting"); this is the same
idea in its simplest, position-based form, run on the device with no host read:

For every triangle, F = Ds Dm^-1 (3x2) has singular values s1 >= s2 (its principal stretches). If
s1 > 1 + limit, the triangle's target shape is F' = F V diag(min(s_i, 1 + limit) / s_i) V^T (the
same rotation and directions, the stretch clamped), placed so that its mass-weighted centroid
stays where it is (the correction carries no momentum). Each vertex moves by the average of
its triangles' corrections (Jacobi), ``iterations`` times; pinned vertices do not move. The
velocity then takes the displacement over the step, v += dx / h, so the next step sees a
consistent state (as the body projection does).

Compression is not limited (cloth buckles out of plane instead). The limit is a numerical
safeguard well above the stretch of healthy frames, not a material law: with it unset (the
default) the solver is the plain backward Euler of :mod:`simgen.sim.solver`.
"""

import functools
from types import SimpleNamespace

import warp as wp

from simgen.errors import InputError
from simgen.sim.warp_toolkit import module_name, scalar_types

__all__ = ["StrainLimiter", "strain_limit_kernels"]


@functools.cache
def strain_limit_kernels(scalar) -> SimpleNamespace:
    """The strain-limiting kernels for one scalar type."""
    T = scalar_types(scalar)
    vec2, vec3, mat22, mat32 = T.vec2, T.vec3, T.mat22, T.mat32
    mod = module_name(__name__, scalar)
    zero = scalar(0.0)
    one = scalar(1.0)

    @wp.kernel(enable_backward=False, module=mod)
    def triangle_corrections(
        x: wp.array(dtype=vec3),
        triangles: wp.array2d(dtype=wp.int32),
        inv_rest: wp.array(dtype=mat22),
        mass: wp.array(dtype=scalar),
        pinned: wp.array(dtype=wp.int32),
        max_stretch: scalar,
        dx: wp.array(dtype=vec3),
        count: wp.array(dtype=scalar),
    ):
        t = wp.tid()
        i0 = triangles[t, 0]
        i1 = triangles[t, 1]
        i2 = triangles[t, 2]
        x0 = x[i0]
        e1 = x[i1] - x0
        e2 = x[i2] - x0
        ds = mat32(e1[0], e2[0], e1[1], e2[1], e1[2], e2[2])
        dm_inv = inv_rest[t]
        f = ds * dm_inv
        c = wp.transpose(f) * f
        # Eigen decomposition of the symmetric 2x2 C = F^T F: stretches s_i = sqrt(lambda_i).
        a = c[0, 0]
        b = c[0, 1]
        d = c[1, 1]
        half = scalar(0.5) * (a - d)
        root = wp.sqrt(half * half + b * b)
        mean = scalar(0.5) * (a + d)
        lam1 = mean + root
        lam2 = wp.max(mean - root, zero)
        s1 = wp.sqrt(lam1)
        if not (s1 > max_stretch):
            return
        # Unit eigenvector of lam1 (the better conditioned of the two closed forms).
        va = vec2(b, lam1 - a)
        vb = vec2(lam1 - d, b)
        v1 = va
        if wp.length_sq(vb) > wp.length_sq(va):
            v1 = vb
        n1 = wp.length(v1)
        if n1 > scalar(1.0e-20):
            v1 = v1 / n1
        else:
            v1 = vec2(one, zero)
        v2 = vec2(-v1[1], v1[0])
        s2 = wp.sqrt(lam2)
        k1 = max_stretch / s1
        k2 = one
        if s2 > max_stretch:
            k2 = max_stretch / s2
        # F' = F V diag(k) V^T.
        scale = mat22(k1 * v1[0] * v1[0] + k2 * v2[0] * v2[0], k1 * v1[0] * v1[1] + k2 * v2[0] * v2[1],
                      k1 * v1[1] * v1[0] + k2 * v2[1] * v2[0], k1 * v1[1] * v1[1] + k2 * v2[1] * v2[1])
        target = f * scale * wp.inverse(dm_inv)        # target edges Ds' (3x2)
        t1 = vec3(target[0, 0], target[1, 0], target[2, 0])
        t2 = vec3(target[0, 1], target[1, 1], target[2, 1])
        # Pinned vertices act as infinitely heavy: the others move around them.
        m0 = mass[i0]
        m1 = mass[i1]
        m2 = mass[i2]
        heavy = scalar(1.0e12)
        if pinned[i0] != 0:
            m0 = heavy
        if pinned[i1] != 0:
            m1 = heavy
        if pinned[i2] != 0:
            m2 = heavy
        total = m0 + m1 + m2
        # x0' so that sum m_i x_i' = sum m_i x_i with x1' = x0' + t1, x2' = x0' + t2.
        shift = (m1 * (e1 - t1) + m2 * (e2 - t2)) / total
        d0 = shift
        d1 = shift + t1 - e1
        d2 = shift + t2 - e2
        wp.atomic_add(dx, i0, d0)
        wp.atomic_add(dx, i1, d1)
        wp.atomic_add(dx, i2, d2)
        wp.atomic_add(count, i0, one)
        wp.atomic_add(count, i1, one)
        wp.atomic_add(count, i2, one)

    @wp.kernel(enable_backward=False, module=mod)
    def apply_corrections(x: wp.array(dtype=vec3), pinned: wp.array(dtype=wp.int32), dx: wp.array(dtype=vec3),
                          count: wp.array(dtype=scalar), moved: wp.array(dtype=vec3)):
        i = wp.tid()
        n = count[i]
        if n > zero and pinned[i] == 0:
            step = dx[i] / n
            x[i] = x[i] + step
            moved[i] = moved[i] + step
        dx[i] = vec3(zero)
        count[i] = zero

    @wp.kernel(enable_backward=False, module=mod)
    def update_velocity(v: wp.array(dtype=vec3), moved: wp.array(dtype=vec3), vertex_instance: wp.array(dtype=wp.int32),
                        step_divisor: wp.array(dtype=wp.int32), inv_h: scalar):
        i = wp.tid()
        v[i] = v[i] + moved[i] * (inv_h * scalar(step_divisor[vertex_instance[i]]))
        moved[i] = vec3(zero)

    return SimpleNamespace(triangle_corrections=triangle_corrections, apply_corrections=apply_corrections,
                           update_velocity=update_velocity)


class StrainLimiter:
    """Strain limiting of one :class:`~simgen.sim.model.ClothModel` (module doc).

    limit [-]: largest allowed principal stretch minus 1 (0.5: no triangle longer than 1.5x its
    rest size in any direction); iterations: Jacobi passes per call. Buffers are allocated here;
    :meth:`apply` launches a fixed sequence (graph-capture safe).
    """

    def __init__(self, model, limit: float, iterations: int = 8) -> None:
        if not (isinstance(limit, (int, float)) and not isinstance(limit, bool) and limit > 0):
            raise InputError(f"strain limit must be a number > 0, got {limit!r}")
        if isinstance(iterations, bool) or not isinstance(iterations, int) or iterations < 1:
            raise InputError(f"strain limit iterations must be an integer >= 1, got {iterations!r}")
        self.model = model
        self.limit = float(limit)
        self.iterations = int(iterations)
        T = scalar_types(model.scalar)
        n, dev = model.num_vertices, model.device
        self._dx = wp.zeros(n, dtype=T.vec3, device=dev)
        self._count = wp.zeros(n, dtype=model.scalar, device=dev)
        self._moved = wp.zeros(n, dtype=T.vec3, device=dev)
        self._kernels = strain_limit_kernels(model.scalar)

    def apply(self, state, h: float | None = None) -> None:
        """Limit the stretch of ``state.positions`` in place; with h [s], add the displacement / h
        to ``state.velocities`` (the step the positions came from took h, divided by each instance's
        ``instance_step_divisor``)."""
        m, k = self.model, self._kernels
        if m.num_triangles == 0:
            return
        for _ in range(self.iterations):
            wp.launch(k.triangle_corrections, dim=m.num_triangles, device=m.device,
                      inputs=[state.positions, m.triangles, m.tri_inv_rest, m.vertex_mass, m.vertex_pinned,
                              m.scalar(1.0 + self.limit), self._dx, self._count])
            wp.launch(k.apply_corrections, dim=m.num_vertices, device=m.device,
                      inputs=[state.positions, m.vertex_pinned, self._dx, self._count, self._moved])
        if h is not None:
            wp.launch(k.update_velocity, dim=m.num_vertices, device=m.device,
                      inputs=[state.velocities, self._moved, m.vertex_instance, m.instance_step_divisor,
                              m.scalar(1.0 / h)])
        else:
            self._moved.zero_()
