"""Plain-numpy float64 reference implementations of the solver's energies (tests, parity checks).

Each function returns per-element energies [J] and the gradient [J/m], shape (V, 3), written from
the formulas independently of the Warp kernels where a second derivation exists:

- membrane: frame-free, from the rest and current edge Gram matrices (no 2D rest frame),
  tr G = tr(M) / 2 and tr G^2 = tr(M^2) / 4 with M = Gbar^-1 C - I;
- contact: brute-force closest points over all body triangles and the sign from the generalised
  winding number (not the pseudo-normal the kernels use);
- the Hessians needed by tests as dense (3V, 3V) matrices (membrane with numpy's eigh for the PSD
  projection instead of the kernels' Jacobi sweeps).
"""

from __future__ import annotations

import numpy as np

__all__ = [
    "dihedral_angles", "dihedral_angle_gradients", "membrane", "membrane_hessian", "bending",
    "bending_hessian_gn", "gravity", "inertia", "closest_points", "winding_numbers", "signed_distance",
    "contact", "friction", "damping",
]


def _wrap(a):
    a = np.asarray(a, dtype=np.float64)
    return np.where(a > np.pi, a - 2 * np.pi, np.where(a <= -np.pi, a + 2 * np.pi, a))


# -- bending ---------------------------------------------------------------------------------------

def dihedral_angles(x, hinges) -> np.ndarray:
    """Signed bending angle [rad] of each hinge (x0, x1, x2, x3), shape (E,), 0 when flat.

    theta = atan2(((N_A x N_B) . e) / |e|, N_A . N_B), e = x1 - x0, N_A = e x (x2 - x0),
    N_B = (x3 - x0) x e.
    """
    x = np.asarray(x, dtype=np.float64)
    h = np.asarray(hinges, dtype=np.int64).reshape(-1, 4)
    x0, x1, x2, x3 = (x[h[:, k]] for k in range(4))
    e = x1 - x0
    na = np.cross(e, x2 - x0)
    nb = np.cross(x3 - x0, e)
    l = np.linalg.norm(e, axis=1)
    return np.arctan2(np.einsum("ij,ij->i", np.cross(na, nb), e) / l, np.einsum("ij,ij->i", na, nb))


def dihedral_angle_gradients(x, hinges) -> np.ndarray:
    """d theta / d(x0, x1, x2, x3), shape (E, 4, 3)."""
    x = np.asarray(x, dtype=np.float64)
    h = np.asarray(hinges, dtype=np.int64).reshape(-1, 4)
    x0, x1, x2, x3 = (x[h[:, k]] for k in range(4))
    e = x1 - x0
    l2 = np.einsum("ij,ij->i", e, e)
    na = np.cross(e, x2 - x0)
    nb = np.cross(x3 - x0, e)
    g2 = -(np.sqrt(l2) / np.einsum("ij,ij->i", na, na))[:, None] * na
    g3 = -(np.sqrt(l2) / np.einsum("ij,ij->i", nb, nb))[:, None] * nb
    sa = (np.einsum("ij,ij->i", x2 - x0, e) / l2)[:, None]
    sb = (np.einsum("ij,ij->i", x3 - x0, e) / l2)[:, None]
    g0 = -(1 - sa) * g2 - (1 - sb) * g3
    g1 = -sa * g2 - sb * g3
    return np.stack([g0, g1, g2, g3], axis=1)


def bending(x, hinges, stiffness, rest_angle) -> tuple[np.ndarray, np.ndarray]:
    """k (theta - theta_rest)^2 / 2 per hinge, shape (E,), and the gradient (V, 3)."""
    x = np.asarray(x, dtype=np.float64)
    h = np.asarray(hinges, dtype=np.int64).reshape(-1, 4)
    k = np.asarray(stiffness, dtype=np.float64)
    delta = _wrap(dihedral_angles(x, h) - rest_angle)
    grad = np.zeros_like(x)
    np.add.at(grad, h.reshape(-1), ((k * delta)[:, None, None] * dihedral_angle_gradients(x, h)).reshape(-1, 3))
    return 0.5 * k * delta**2, grad


def bending_hessian_gn(x, hinges, stiffness) -> np.ndarray:
    """Gauss-Newton bending Hessian sum_e k_e grad(theta) grad(theta)^T, dense (3V, 3V)."""
    x = np.asarray(x, dtype=np.float64)
    h = np.asarray(hinges, dtype=np.int64).reshape(-1, 4)
    g = dihedral_angle_gradients(x, h).reshape(len(h), 12)
    out = np.zeros((3 * len(x), 3 * len(x)))
    for e in range(len(h)):
        idx = (3 * h[e][:, None] + np.arange(3)).reshape(-1)
        out[np.ix_(idx, idx)] += stiffness[e] * np.outer(g[e], g[e])
    return out


# -- membrane --------------------------------------------------------------------------------------

def membrane(x, rest, faces, lam_h, mu_h) -> tuple[np.ndarray, np.ndarray]:
    """StVK energy A (lam_h/2 tr(G)^2 + mu_h tr(G^2)) per triangle, shape (F,), and gradient (V, 3).

    Frame-free: with rest edge Gram Gbar = Dr^T Dr and current C = Ds^T Ds (Dr, Ds: 3x2 edge
    matrices), M = Gbar^-1 C - I, tr G = tr(M)/2, tr G^2 = tr(M^2)/4, A = sqrt(det Gbar)/2, and
    dE/dDs = A Ds Gbar^-1 (lam_h/2 tr(M) I + mu_h (C Gbar^-1 - I)).
    """
    x = np.asarray(x, dtype=np.float64)
    rest = np.asarray(rest, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    dr = np.stack([rest[f[:, 1]] - rest[f[:, 0]], rest[f[:, 2]] - rest[f[:, 0]]], axis=2)  # (F, 3, 2)
    ds = np.stack([x[f[:, 1]] - x[f[:, 0]], x[f[:, 2]] - x[f[:, 0]]], axis=2)
    gbar = np.einsum("fki,fkj->fij", dr, dr)
    c = np.einsum("fki,fkj->fij", ds, ds)
    gbar_inv = np.linalg.inv(gbar)
    area = 0.5 * np.sqrt(np.linalg.det(gbar))
    eye = np.eye(2)
    m = gbar_inv @ c - eye
    tr_m = np.trace(m, axis1=1, axis2=2)
    tr_m2 = np.einsum("fij,fji->f", m, m)
    lam_h = np.asarray(lam_h, dtype=np.float64)
    mu_h = np.asarray(mu_h, dtype=np.float64)
    energy = area * (lam_h / 8.0 * tr_m**2 + mu_h / 4.0 * tr_m2)
    inner = (lam_h / 2.0 * tr_m)[:, None, None] * eye + mu_h[:, None, None] * (c @ gbar_inv - eye)
    d_ds = area[:, None, None] * (ds @ gbar_inv @ inner)  # (F, 3, 2)
    grad = np.zeros_like(x)
    np.add.at(grad, f[:, 1], d_ds[:, :, 0])
    np.add.at(grad, f[:, 2], d_ds[:, :, 1])
    np.add.at(grad, f[:, 0], -(d_ds[:, :, 0] + d_ds[:, :, 1]))
    return energy, grad


def _stvk_hessian_f(F, lam, mu):
    """d2 Psi / dF2 (6x6, index 3c + i) of StVK at a 3x2 F."""
    G = 0.5 * (F.T @ F - np.eye(2))
    S = lam * np.trace(G) * np.eye(2) + 2 * mu * G
    FFt = F @ F.T
    H = np.zeros((6, 6))
    for c in range(2):
        for d in range(2):
            blk = lam * np.outer(F[:, c], F[:, d]) + mu * np.outer(F[:, d], F[:, c]) + S[c, d] * np.eye(3)
            if c == d:
                blk += mu * FFt
            H[3 * c:3 * c + 3, 3 * d:3 * d + 3] = blk
    return H


def membrane_hessian(x, rest, faces, lam_h, mu_h, *, project: bool = True) -> np.ndarray:
    """Membrane Hessian, dense (3V, 3V): per triangle A D^T H D with H = d2Psi/dF2 (clamped to PSD
    by numpy's eigh if ``project``) and D = dF/dx, in a QR rest frame of each triangle."""
    x = np.asarray(x, dtype=np.float64)
    rest = np.asarray(rest, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    out = np.zeros((3 * len(x), 3 * len(x)))
    for t, tri in enumerate(f):
        dr = np.stack([rest[tri[1]] - rest[tri[0]], rest[tri[2]] - rest[tri[0]]], axis=1)
        _, r = np.linalg.qr(dr)
        r_inv = np.linalg.inv(r)
        area = 0.5 * abs(np.linalg.det(r))
        ds = np.stack([x[tri[1]] - x[tri[0]], x[tri[2]] - x[tri[0]]], axis=1)
        H = _stvk_hessian_f(ds @ r_inv, lam_h[t], mu_h[t])
        if project:
            w, v = np.linalg.eigh(H)
            H = (v * np.maximum(w, 0.0)) @ v.T
        wv = np.array([-(r_inv[0] + r_inv[1]), r_inv[0], r_inv[1]])  # (3 vertices, 2 columns)
        D = np.zeros((6, 9))
        for v_ in range(3):
            for c in range(2):
                D[3 * c:3 * c + 3, 3 * v_:3 * v_ + 3] = wv[v_, c] * np.eye(3)
        idx = (3 * tri[:, None] + np.arange(3)).reshape(-1)
        out[np.ix_(idx, idx)] += area * D.T @ H @ D
    return out


# -- gravity, inertia ------------------------------------------------------------------------------

def gravity(x, mass, g=(0.0, -9.81, 0.0)) -> tuple[np.ndarray, np.ndarray]:
    """-m g . x per vertex, shape (V,), and gradient -m g, (V, 3)."""
    x = np.asarray(x, dtype=np.float64)
    m = np.asarray(mass, dtype=np.float64)
    g = np.asarray(g, dtype=np.float64)
    return -m * (x @ g), -m[:, None] * g[None, :]


def inertia(x, x_hat, mass, dt) -> tuple[np.ndarray, np.ndarray]:
    """m |x - x_hat|^2 / (2 h^2) per vertex and gradient m (x - x_hat) / h^2."""
    d = np.asarray(x, dtype=np.float64) - np.asarray(x_hat, dtype=np.float64)
    k = np.asarray(mass, dtype=np.float64) / dt**2
    return 0.5 * k * np.sum(d * d, axis=1), k[:, None] * d


# -- body contact ----------------------------------------------------------------------------------

def _closest_on_segments(p, a, b):
    ab = b - a
    t = np.clip(np.einsum("ij,ij->i", p - a, ab) / np.maximum(np.einsum("ij,ij->i", ab, ab), 1e-300), 0.0, 1.0)
    return a + t[:, None] * ab


def closest_points(points, body_vertices, body_faces) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Brute force: unsigned distance (P,), closest point (P, 3) and face (P,) on a triangle mesh.

    The closest point of a triangle is the plane projection when it falls inside, else the
    nearest point of its three edges.
    """
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    bv = np.asarray(body_vertices, dtype=np.float64)
    bf = np.asarray(body_faces, dtype=np.int64)
    a, b, c = bv[bf[:, 0]], bv[bf[:, 1]], bv[bf[:, 2]]
    n = np.cross(b - a, c - a)
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    dist = np.zeros(len(pts))
    closest = np.zeros((len(pts), 3))
    face = np.zeros(len(pts), dtype=np.int64)
    for k, p in enumerate(pts):
        pp = np.broadcast_to(p, a.shape)
        proj = p - np.einsum("ij,ij->i", p - a, n)[:, None] * n
        # Inside test: the projection is on the inner side of all three edges.
        inside = np.ones(len(bf), dtype=bool)
        for u, v in ((a, b), (b, c), (c, a)):
            inside &= np.einsum("ij,ij->i", np.cross(v - u, proj - u), n) >= 0
        cand = [np.where(inside[:, None], proj, np.inf)]
        for u, v in ((a, b), (b, c), (c, a)):
            cand.append(_closest_on_segments(pp, u, v))
        cand = np.stack(cand)  # (4, F, 3)
        d2 = np.sum((cand - p) ** 2, axis=2)
        best = np.unravel_index(np.argmin(d2), d2.shape)
        dist[k] = np.sqrt(d2[best])
        closest[k] = cand[best]
        face[k] = best[1]
    return dist, closest, face


def winding_numbers(points, body_vertices, body_faces) -> np.ndarray:
    """Generalised winding number of a closed mesh at each point (P,) (van Oosterom-Strackee)."""
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    bv = np.asarray(body_vertices, dtype=np.float64)
    bf = np.asarray(body_faces, dtype=np.int64)
    out = np.zeros(len(pts))
    for k, p in enumerate(pts):
        a, b, c = bv[bf[:, 0]] - p, bv[bf[:, 1]] - p, bv[bf[:, 2]] - p
        la, lb, lc = (np.linalg.norm(v, axis=1) for v in (a, b, c))
        num = np.einsum("ij,ij->i", a, np.cross(b, c))
        den = (la * lb * lc + np.einsum("ij,ij->i", a, b) * lc + np.einsum("ij,ij->i", b, c) * la
               + np.einsum("ij,ij->i", c, a) * lb)
        out[k] = np.sum(2.0 * np.arctan2(num, den)) / (4.0 * np.pi)
    return out


def signed_distance(points, body_vertices, body_faces) -> tuple[np.ndarray, np.ndarray]:
    """Signed distance (P,), negative inside (winding number > 1/2), and the outward normal (P, 3)."""
    dist, closest, face = closest_points(points, body_vertices, body_faces)
    sign = np.where(winding_numbers(points, body_vertices, body_faces) > 0.5, -1.0, 1.0)
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    diff = pts - closest
    bv = np.asarray(body_vertices, dtype=np.float64)
    bf = np.asarray(body_faces, dtype=np.int64)[face]
    nf = np.cross(bv[bf[:, 1]] - bv[bf[:, 0]], bv[bf[:, 2]] - bv[bf[:, 0]])
    nf /= np.linalg.norm(nf, axis=1, keepdims=True)
    safe = dist > 1e-12
    normal = np.where(safe[:, None], sign[:, None] * diff / np.where(safe, dist, 1.0)[:, None], nf)
    return sign * dist, normal


def contact(x, body_vertices, body_faces, margin, stiffness, power) -> tuple[np.ndarray, np.ndarray]:
    """k max(margin - d, 0)^p per vertex (V,) and gradient -k p (margin - d)^(p-1) n, (V, 3)."""
    d, n = signed_distance(x, body_vertices, body_faces)
    pen = np.maximum(margin - d, 0.0)
    return stiffness * pen**power, -(stiffness * power * pen ** (power - 1))[:, None] * n


# -- friction, damping -----------------------------------------------------------------------------

def friction(x, x_start, normal, force, mu, body_displacement, eps) -> tuple[np.ndarray, np.ndarray]:
    """Lagged smoothed friction mu lambda f0(|P (x - x_t - db)|) per vertex and its gradient.

    normal (V, 3) and force lambda (V,) [N] frozen; body_displacement db [m] (V, 3) = h v_body;
    eps = eps_v h [m]; f0 is IPC's mollifier (see :mod:`simgen.sim.energies.friction`).
    """
    x = np.asarray(x, dtype=np.float64)
    n = np.asarray(normal, dtype=np.float64)
    c = np.asarray(mu, dtype=np.float64) * np.asarray(force, dtype=np.float64)
    disp = x - np.asarray(x_start, dtype=np.float64) - np.asarray(body_displacement, dtype=np.float64)
    u = disp - np.sum(disp * n, axis=1, keepdims=True) * n
    y = np.linalg.norm(u, axis=1)
    stick = y < eps
    f0 = np.where(stick, -y**3 / (3 * eps**2) + y**2 / eps + eps / 3, y)
    f1_over_y = np.where(stick, 2 / eps - y / eps**2, 1.0 / np.where(stick, 1.0, y))
    return np.where(c > 0, c * f0, 0.0), (c * f1_over_y)[:, None] * u


def damping(x, x_start, dt, *, rest, faces, lam_h, mu_h, beta_tri, hinges, hinge_stiffness, beta_hinge,
            mass, alpha) -> tuple[float, np.ndarray]:
    """Total damping potential (membrane + bending + mass parts) [J] and its gradient (V, 3).

    Membrane: (beta/h) A Psi(G(x) - G(x_t)), G in a per-triangle QR rest frame; bending:
    (beta/h) k (theta(x) - theta(x_t))^2 / 2; mass: alpha m |x - x_t|^2 / (2h).
    """
    x = np.asarray(x, dtype=np.float64)
    xs = np.asarray(x_start, dtype=np.float64)
    rest = np.asarray(rest, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    energy = 0.0
    grad = np.zeros_like(x)
    for t, tri in enumerate(f):
        c = beta_tri[t] / dt
        if c <= 0:
            continue
        dr = np.stack([rest[tri[1]] - rest[tri[0]], rest[tri[2]] - rest[tri[0]]], axis=1)
        _, r = np.linalg.qr(dr)
        r_inv = np.linalg.inv(r)
        area = 0.5 * abs(np.linalg.det(r))
        F = np.stack([x[tri[1]] - x[tri[0]], x[tri[2]] - x[tri[0]]], axis=1) @ r_inv
        F0 = np.stack([xs[tri[1]] - xs[tri[0]], xs[tri[2]] - xs[tri[0]]], axis=1) @ r_inv
        dG = 0.5 * (F.T @ F - F0.T @ F0)
        energy += c * area * (0.5 * lam_h[t] * np.trace(dG) ** 2 + mu_h[t] * np.sum(dG * dG))
        S = lam_h[t] * np.trace(dG) * np.eye(2) + 2 * mu_h[t] * dG
        d_ds = c * area * (F @ S) @ r_inv.T
        grad[tri[1]] += d_ds[:, 0]
        grad[tri[2]] += d_ds[:, 1]
        grad[tri[0]] -= d_ds[:, 0] + d_ds[:, 1]
    h = np.asarray(hinges, dtype=np.int64).reshape(-1, 4)
    if len(h):
        k = np.asarray(beta_hinge, dtype=np.float64) / dt * np.asarray(hinge_stiffness, dtype=np.float64)
        delta = _wrap(dihedral_angles(x, h) - dihedral_angles(xs, h))
        energy += float(np.sum(0.5 * k * delta**2))
        np.add.at(grad, h.reshape(-1), ((k * delta)[:, None, None] * dihedral_angle_gradients(x, h)).reshape(-1, 3))
    km = np.asarray(alpha, dtype=np.float64) * np.asarray(mass, dtype=np.float64) / dt
    d = x - xs
    energy += float(np.sum(0.5 * km * np.sum(d * d, axis=1)))
    grad += km[:, None] * d
    return energy, grad
