"""Linear elasticity on tetrahedra, the flesh's internal force, as Warp kernels (float32).

Per tetrahedron with rest nodes X0..X3 [m]: Dm = [X1 - X0, X2 - X0, X3 - X0], Bm = Dm^-1 and the
volume V = |det Dm| / 6 [m^3]. A displacement field u [m] has the constant gradient G = Ds(u) Bm
with Ds(u) = [u1 - u0, u2 - u0, u3 - u0]; the small strain eps = (G + G^T) / 2, the stress
sigma = 2 mu eps + lam tr(eps) I [Pa] and the energy V (mu eps:eps + lam / 2 tr(eps)^2) [J]. The
gradient of the shape function N_a is row a - 1 of Bm for a = 1..3 and minus their sum for a = 0,
so the force on node a is -V sigma grad N_a, and the stiffness's diagonal block of node a is
V (mu |b|^2 I + (mu + lam) b b^T) with b = grad N_a.

K is applied matrix-free: one thread per tetrahedron adds -f(u) into its four nodes (atomics).
"""

from __future__ import annotations

import numpy as np
import warp as wp

__all__ = ["apply_stiffness", "stiffness_diagonal", "rest_shape", "lame"]


def lame(young: np.ndarray, poisson: float) -> tuple[np.ndarray, np.ndarray]:
    """Lamé parameters mu, lam [Pa] of Young's modulus [Pa] (any shape) and Poisson's ratio."""
    e = np.asarray(young, dtype=np.float64)
    nu = float(poisson)
    return e / (2.0 * (1.0 + nu)), e * nu / ((1.0 + nu) * (1.0 - 2.0 * nu))


def rest_shape(nodes: np.ndarray, tets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Bm = Dm^-1 (T, 3, 3) and the signed volume [m^3] (T,) of each tetrahedron of ``nodes`` [m] (N, 3)
    and ``tets`` (T, 4) (positive when X1 - X0, X2 - X0, X3 - X0 are right-handed)."""
    x = np.asarray(nodes, dtype=np.float64)[np.asarray(tets)]
    dm = np.stack([x[:, 1] - x[:, 0], x[:, 2] - x[:, 0], x[:, 3] - x[:, 0]], axis=2)   # columns
    det = np.linalg.det(dm)
    return np.linalg.inv(dm), det / 6.0


@wp.func
def _grads(bm: wp.mat33):
    b1 = wp.vec3(bm[0, 0], bm[0, 1], bm[0, 2])
    b2 = wp.vec3(bm[1, 0], bm[1, 1], bm[1, 2])
    b3 = wp.vec3(bm[2, 0], bm[2, 1], bm[2, 2])
    return -(b1 + b2 + b3), b1, b2, b3


@wp.kernel(enable_backward=False)
def apply_stiffness(u: wp.array(dtype=wp.vec3), tets: wp.array(dtype=wp.vec4i), inv_rest: wp.array(dtype=wp.mat33),
                    volume: wp.array(dtype=wp.float32), mu: wp.array(dtype=wp.float32),
                    lam: wp.array(dtype=wp.float32), out: wp.array(dtype=wp.vec3)):
    """out += K u, one thread per tetrahedron (zero ``out`` first)."""
    t = wp.tid()
    e = tets[t]
    b0, b1, b2, b3 = _grads(inv_rest[t])
    g = wp.outer(u[e[0]], b0) + wp.outer(u[e[1]], b1) + wp.outer(u[e[2]], b2) + wp.outer(u[e[3]], b3)
    eps = 0.5 * (g + wp.transpose(g))
    tr = eps[0, 0] + eps[1, 1] + eps[2, 2]
    sigma = 2.0 * mu[t] * eps + lam[t] * tr * wp.identity(n=3, dtype=wp.float32)
    v = volume[t]
    wp.atomic_add(out, e[0], v * (sigma * b0))
    wp.atomic_add(out, e[1], v * (sigma * b1))
    wp.atomic_add(out, e[2], v * (sigma * b2))
    wp.atomic_add(out, e[3], v * (sigma * b3))


@wp.func
def _block(b: wp.vec3, v: float, mu: float, lam: float):
    return v * (mu * wp.dot(b, b) * wp.identity(n=3, dtype=wp.float32) + (mu + lam) * wp.outer(b, b))


@wp.kernel(enable_backward=False)
def stiffness_diagonal(tets: wp.array(dtype=wp.vec4i), inv_rest: wp.array(dtype=wp.mat33),
                       volume: wp.array(dtype=wp.float32), mu: wp.array(dtype=wp.float32),
                       lam: wp.array(dtype=wp.float32), out: wp.array(dtype=wp.mat33)):
    """out += the 3x3 diagonal blocks of K, one thread per tetrahedron (zero ``out`` first)."""
    t = wp.tid()
    e = tets[t]
    b0, b1, b2, b3 = _grads(inv_rest[t])
    v, m, l = volume[t], mu[t], lam[t]
    wp.atomic_add(out, e[0], _block(b0, v, m, l))
    wp.atomic_add(out, e[1], _block(b1, v, m, l))
    wp.atomic_add(out, e[2], _block(b2, v, m, l))
    wp.atomic_add(out, e[3], _block(b3, v, m, l))
