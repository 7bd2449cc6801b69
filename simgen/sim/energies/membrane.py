"""StVK membrane energy (SNUG eqs. 5.8-5.9), its gradient and PSD-projected Hessian.

Per triangle t with rest area A_t, thickness folded into the Lame coefficients (lambda h, mu h
[N/m], plane stress):

    E_t = A_t * (lambda h / 2 tr(G)^2 + mu h tr(G^2)),   G = (F^T F - I) / 2,   F = Ds Dm^-1,

Ds = [x1 - x0, x2 - x0] (3x2, current), Dm the rest edges in the triangle's own 2D frame. With
S = lambda tr(G) I + 2 mu G (second Piola-Kirchhoff) and P = F S, dE/dDs = A P Dm^-T. The
Hessian of the energy density with respect to vec(F) = (F[:, 0], F[:, 1]) is the 6x6

    H[(c, i), (d, j)] = delta_ij S_cd + lambda F_ic F_jd + mu (delta_cd (F F^T)_ij + F_id F_jc),

PSD whenever S is (stretch). In compression it is projected to PSD (eigenvalues clamped at 0 by a
6x6 Jacobi eigen-decomposition) and mapped to the 9x9 vertex Hessian with the constant dF/dx:
A D^T H+ D is PSD because H+ is.
"""

import functools
from types import SimpleNamespace

import warp as wp

from simgen.sim.warp_toolkit import (launch_blocked, math_funcs, module_name, reduce_funcs, resolve_outputs,
                                         scalar_types)

__all__ = ["eval_membrane", "membrane_funcs", "membrane_kernels"]


@functools.cache
def membrane_funcs(scalar) -> SimpleNamespace:
    """Warp functions of the StVK membrane for one scalar type (shared with the damping term).

    deformation_gradient(x0, x1, x2, Dm^-1) -> F (3x2); green_strain(F) -> G (2x2);
    stvk_density(G, lam, mu) -> Psi; stvk_stress(G, lam, mu) -> S; stvk_hessian(F, S, lam, mu) -> 6x6;
    s_is_psd(S) -> bool; add_triangle_gradient(grad, i0, i1, i2, P, Dm^-1, area);
    add_triangle_hessian(hess, slots, t, H6, Dm^-1, area).
    """
    T = scalar_types(scalar)
    vec3, mat22, mat33, mat32, mat66 = T.vec3, T.mat22, T.mat33, T.mat32, T.mat66
    zero = scalar(0.0)
    half = scalar(0.5)

    @wp.func
    def deformation_gradient(x0: vec3, x1: vec3, x2: vec3, dm_inv: mat22):
        e1 = x1 - x0
        e2 = x2 - x0
        ds = mat32(e1[0], e2[0], e1[1], e2[1], e1[2], e2[2])
        return ds * dm_inv

    @wp.func
    def green_strain(f: mat32):
        c = wp.transpose(f) * f
        return mat22(half * (c[0, 0] - scalar(1.0)), half * c[0, 1], half * c[1, 0], half * (c[1, 1] - scalar(1.0)))

    @wp.func
    def stvk_density(g: mat22, lam: scalar, mu: scalar):
        tr = g[0, 0] + g[1, 1]
        tr_g2 = g[0, 0] * g[0, 0] + g[0, 1] * g[1, 0] + g[1, 0] * g[0, 1] + g[1, 1] * g[1, 1]
        return half * lam * tr * tr + mu * tr_g2

    @wp.func
    def stvk_stress(g: mat22, lam: scalar, mu: scalar):
        tr = g[0, 0] + g[1, 1]
        return mat22(lam * tr + scalar(2.0) * mu * g[0, 0], scalar(2.0) * mu * g[0, 1],
                     scalar(2.0) * mu * g[1, 0], lam * tr + scalar(2.0) * mu * g[1, 1])

    @wp.func
    def s_is_psd(s: mat22):
        # A symmetric 2x2 is PSD iff its trace and determinant are both >= 0.
        return (s[0, 0] + s[1, 1] >= zero) and (s[0, 0] * s[1, 1] - s[0, 1] * s[1, 0] >= zero)

    @wp.func
    def stvk_hessian(f: mat32, s: mat22, lam: scalar, mu: scalar):
        ffT = f * wp.transpose(f)
        h = mat66()
        for c in range(2):
            for d in range(2):
                for i in range(3):
                    for j in range(3):
                        v = lam * f[i, c] * f[j, d] + mu * f[i, d] * f[j, c]
                        if i == j:
                            v += s[c, d]
                        if c == d:
                            v += mu * ffT[i, j]
                        h[3 * c + i, 3 * d + j] = v
        return h

    @wp.func
    def add_triangle_gradient(grad: wp.array(dtype=vec3), i0: int, i1: int, i2: int, p: mat32,
                              dm_inv: mat22, area: scalar):
        # dE/dDs = A P Dm^-T: its columns are the gradients of x1 and x2; x0 balances them.
        g = area * (p * wp.transpose(dm_inv))
        g1 = vec3(g[0, 0], g[1, 0], g[2, 0])
        g2 = vec3(g[0, 1], g[1, 1], g[2, 1])
        wp.atomic_add(grad, i0, -(g1 + g2))
        wp.atomic_add(grad, i1, g1)
        wp.atomic_add(grad, i2, g2)

    @wp.func
    def add_triangle_hessian(hess: wp.array(dtype=mat33), slots: wp.array2d(dtype=wp.int32), t: int,
                             h: mat66, dm_inv: mat22, area: scalar):
        # dF[:, c]/dx_v = w[v, c] I with w[1] = row 0 of Dm^-1, w[2] = row 1, w[0] = -(w[1] + w[2]),
        # so block (v, u) = A sum_cd w[v, c] w[u, d] H_cd, H_cd the 3x3 sub-block (c, d) of H.
        w = mat32(-(dm_inv[0, 0] + dm_inv[1, 0]), -(dm_inv[0, 1] + dm_inv[1, 1]),
                  dm_inv[0, 0], dm_inv[0, 1],
                  dm_inv[1, 0], dm_inv[1, 1])
        h00 = mat33()
        h01 = mat33()
        h10 = mat33()
        h11 = mat33()
        for i in range(3):
            for j in range(3):
                h00[i, j] = h[i, j]
                h01[i, j] = h[i, 3 + j]
                h10[i, j] = h[3 + i, j]
                h11[i, j] = h[3 + i, 3 + j]
        for v in range(3):
            for u in range(3):
                block = area * (w[v, 0] * w[u, 0] * h00 + w[v, 0] * w[u, 1] * h01
                                + w[v, 1] * w[u, 0] * h10 + w[v, 1] * w[u, 1] * h11)
                wp.atomic_add(hess, slots[t, 3 * v + u], block)

    return SimpleNamespace(
        deformation_gradient=deformation_gradient, green_strain=green_strain, stvk_density=stvk_density,
        stvk_stress=stvk_stress, stvk_hessian=stvk_hessian, s_is_psd=s_is_psd,
        add_triangle_gradient=add_triangle_gradient, add_triangle_hessian=add_triangle_hessian,
    )


@functools.cache
def membrane_kernels(scalar) -> SimpleNamespace:
    """The membrane kernel for one scalar type (``.membrane``, one thread per triangle, launched in
    blocks: the energy is a block reduction per instance)."""
    T = scalar_types(scalar)
    vec3, mat22, mat33 = T.vec3, T.mat22, T.mat33
    fn = membrane_funcs(scalar)
    project_psd6 = math_funcs(scalar).project_psd6
    block_add = reduce_funcs(scalar).block_add

    @wp.kernel(enable_backward=False, module=module_name(__name__, scalar))
    def membrane(
        x: wp.array(dtype=vec3),
        tris: wp.array2d(dtype=wp.int32),
        inv_rest: wp.array(dtype=mat22),
        rest_area: wp.array(dtype=scalar),
        lam: wp.array(dtype=scalar),
        mu: wp.array(dtype=scalar),
        tri_instance: wp.array(dtype=wp.int32),
        instance_active: wp.array(dtype=wp.int32),
        tri_slots: wp.array2d(dtype=wp.int32),
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
        e = scalar(0.0)
        live = False
        if t < n:
            live = instance_active[tri_instance[t]] != 0
        if live:
            i0 = tris[t, 0]
            i1 = tris[t, 1]
            i2 = tris[t, 2]
            dm_inv = inv_rest[t]
            area = rest_area[t] * scale
            f = fn.deformation_gradient(x[i0], x[i1], x[i2], dm_inv)
            g = fn.green_strain(f)
            e = area * fn.stvk_density(g, lam[t], mu[t])
            if want_grad != 0 or want_hess != 0:
                s = fn.stvk_stress(g, lam[t], mu[t])
                if want_grad != 0:
                    fn.add_triangle_gradient(grad, i0, i1, i2, f * s, dm_inv, area)
                if want_hess != 0:
                    h = fn.stvk_hessian(f, s, lam[t], mu[t])
                    if project != 0 and not fn.s_is_psd(s):
                        h = project_psd6(h)
                    fn.add_triangle_hessian(hess, tri_slots, t, h, dm_inv, area)
        if want_energy != 0:  # uniform over the launch, so every thread of a block reaches the tile sum
            block_add(energy, tri_instance, block, lane, t, n, e)

    return SimpleNamespace(membrane=membrane)


def eval_membrane(model, positions, *, energy=None, gradient=None, hessian=None, scale: float = 1.0,
                  project: bool = True) -> None:
    """Accumulate the StVK membrane energy of every triangle of ``model``.

    positions [m], (V,) vec3 warp array of the model's scalar type. Outputs are added to (never
    zeroed here), each optional: energy [J], (num_instances,) per-instance sums; gradient [J/m],
    (V,) vec3; hessian [J/m^2]: the model's BsrMatrix (or its (nnz,) mat33 values). scale
    multiplies all three (e.g. h^2 for a mass-scaled system). project=False keeps the exact,
    possibly indefinite Hessian (tests).
    """
    we, wg, wh, e, g, h = resolve_outputs(energy, gradient, hessian)
    if model.num_triangles == 0 or not (we or wg or wh):
        return
    k = membrane_kernels(model.scalar).membrane
    launch_blocked(k, model.num_triangles, model.device, [
        positions, model.triangles, model.tri_inv_rest, model.tri_rest_area, model.tri_lambda, model.tri_mu,
        model.tri_instance, model.instance_active, model.tri_slots, scale, int(project), we, wg, wh, e, g, h])
