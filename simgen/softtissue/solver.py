"""The flesh's integrator: Newmark's average-acceleration rule (beta = 1/4, gamma = 1/2, the
trapezoidal rule) on  M a + C v + K u = f  with Rayleigh damping C = a_M M + a_K K, solved by a
block-Jacobi PCG in Warp with per-instance scalars (instances never couple).

For a linear system without damping the rule conserves the energy 1/2 v^T M v + 1/2 u^T K u - f^T u
exactly (up to the PCG's tolerance) at any step and is unconditionally stable: it neither gains
nor quietly loses energy; the damping is the material's, set in :class:`FleshParams`. Pinned nodes
keep u = v = a = 0.

One step from (u, v, a) with step h and the force f of the step's end:
    u~ = u + h v + h^2 / 4 a,   v~ = v + h / 2 a
    (c_M M + c_K K) a' = f - a_M M v~ - K (u~ + a_K v~),   c_M = 1 + h a_M / 2,  c_K = h a_K / 2 + h^2 / 4
    u' = u~ + h^2 / 4 a',   v' = v~ + h / 2 a'
"""

from __future__ import annotations

import numpy as np
import warp as wp

from simgen.softtissue.elastic import apply_stiffness, stiffness_diagonal
from simgen.softtissue.model import FleshModel

__all__ = ["FleshSolver"]


@wp.kernel(enable_backward=False)
def _combine(x: wp.array(dtype=wp.vec3), kx: wp.array(dtype=wp.vec3), mass: wp.array(dtype=wp.float32),
             pinned: wp.array(dtype=wp.int32), cm: float, ck: float, y: wp.array(dtype=wp.vec3)):
    i = wp.tid()
    if pinned[i] != 0:
        y[i] = wp.vec3(0.0)
    else:
        y[i] = cm * mass[i] * x[i] + ck * kx[i]


@wp.kernel(enable_backward=False)
def _residual(rhs: wp.array(dtype=wp.vec3), ax: wp.array(dtype=wp.vec3), pinned: wp.array(dtype=wp.int32),
              r: wp.array(dtype=wp.vec3)):
    i = wp.tid()
    if pinned[i] != 0:
        r[i] = wp.vec3(0.0)
    else:
        r[i] = rhs[i] - ax[i]


@wp.kernel(enable_backward=False)
def _instance_dot(a: wp.array(dtype=wp.vec3), b: wp.array(dtype=wp.vec3), node_instance: wp.array(dtype=wp.int32),
                  out: wp.array(dtype=wp.float64)):
    i = wp.tid()
    wp.atomic_add(out, node_instance[i], wp.float64(wp.dot(a[i], b[i])))


@wp.kernel(enable_backward=False)
def _precondition(r: wp.array(dtype=wp.vec3), mass: wp.array(dtype=wp.float32), diag: wp.array(dtype=wp.mat33),
                  pinned: wp.array(dtype=wp.int32), cm: float, ck: float, z: wp.array(dtype=wp.vec3)):
    i = wp.tid()
    if pinned[i] != 0:
        z[i] = wp.vec3(0.0)
    else:
        block = cm * mass[i] * wp.identity(n=3, dtype=wp.float32) + ck * diag[i]
        z[i] = wp.inverse(block) * r[i]


@wp.kernel(enable_backward=False)
def _step_x_r(x: wp.array(dtype=wp.vec3), r: wp.array(dtype=wp.vec3), p: wp.array(dtype=wp.vec3),
              ap: wp.array(dtype=wp.vec3), node_instance: wp.array(dtype=wp.int32), rz: wp.array(dtype=wp.float64),
              pap: wp.array(dtype=wp.float64)):
    i = wp.tid()
    k = node_instance[i]
    alpha = float(0.0)
    if pap[k] > wp.float64(0.0):
        alpha = float(rz[k] / pap[k])
    x[i] = x[i] + alpha * p[i]
    r[i] = r[i] - alpha * ap[i]


@wp.kernel(enable_backward=False)
def _step_p(p: wp.array(dtype=wp.vec3), z: wp.array(dtype=wp.vec3), node_instance: wp.array(dtype=wp.int32),
            rz_new: wp.array(dtype=wp.float64), rz_old: wp.array(dtype=wp.float64)):
    i = wp.tid()
    k = node_instance[i]
    beta = float(0.0)
    if rz_old[k] > wp.float64(0.0):
        beta = float(rz_new[k] / rz_old[k])
    p[i] = z[i] + beta * p[i]


@wp.kernel(enable_backward=False)
def _predict(u: wp.array(dtype=wp.vec3), v: wp.array(dtype=wp.vec3), a: wp.array(dtype=wp.vec3), h: float,
             a_k: float, u_pred: wp.array(dtype=wp.vec3), v_pred: wp.array(dtype=wp.vec3),
             probe: wp.array(dtype=wp.vec3)):
    i = wp.tid()
    up = u[i] + h * v[i] + 0.25 * h * h * a[i]
    vp = v[i] + 0.5 * h * a[i]
    u_pred[i] = up
    v_pred[i] = vp
    probe[i] = up + a_k * vp


@wp.kernel(enable_backward=False)
def _step_rhs(f: wp.array(dtype=wp.vec3), v_pred: wp.array(dtype=wp.vec3), k_probe: wp.array(dtype=wp.vec3),
              mass: wp.array(dtype=wp.float32), pinned: wp.array(dtype=wp.int32), a_m: float,
              rhs: wp.array(dtype=wp.vec3)):
    i = wp.tid()
    if pinned[i] != 0:
        rhs[i] = wp.vec3(0.0)
    else:
        rhs[i] = f[i] - a_m * mass[i] * v_pred[i] - k_probe[i]


@wp.kernel(enable_backward=False)
def _correct(u_pred: wp.array(dtype=wp.vec3), v_pred: wp.array(dtype=wp.vec3), a: wp.array(dtype=wp.vec3),
             h: float, u: wp.array(dtype=wp.vec3), v: wp.array(dtype=wp.vec3)):
    i = wp.tid()
    u[i] = u_pred[i] + 0.25 * h * h * a[i]
    v[i] = v_pred[i] + 0.5 * h * a[i]


class FleshSolver:
    """State and integrator of a :class:`FleshModel`.

    ``u`` [m], ``v`` [m/s], ``a`` [m/s^2]: (N*Nn,) wp.vec3, the displacement in the unposed frame and
    its rates; ``cg_iterations``: PCG iterations of the last solve (the largest over instances, in
    rounds of 8); ``cg_capped``: solves that reached ``params.cg_iterations`` unconverged.
    """

    def __init__(self, model: FleshModel) -> None:
        self.model = m = model
        dev, n = m.device, m.total_nodes
        self.u, self.v, self.a = (wp.zeros(n, dtype=wp.vec3, device=dev) for _ in range(3))
        self._tmp = {k: wp.zeros(n, dtype=wp.vec3, device=dev)
                     for k in ("u_pred", "v_pred", "probe", "kx", "rhs", "r", "z", "p", "ap")}
        self._dots = {k: wp.zeros(m.num_instances, dtype=wp.float64, device=dev) for k in ("rz", "rz_new", "pap", "rr")}
        self.diag = wp.zeros(n, dtype=wp.mat33, device=dev)
        wp.launch(stiffness_diagonal, dim=m.num_tets_total, device=dev,
                  inputs=[m.tets, m.inv_rest, m.volume, m.mu, m.lam], outputs=[self.diag])
        self.cg_iterations = 0
        self.cg_capped = 0      # solves that stopped at params.cg_iterations (checked every 8)

    # -- operators ----------------------------------------------------------------------------------
    def stiffness(self, x: wp.array, out: wp.array) -> wp.array:
        """out = K x (no pins applied), (N*Nn,) vec3."""
        m = self.model
        out.zero_()
        wp.launch(apply_stiffness, dim=m.num_tets_total, device=m.device,
                  inputs=[x, m.tets, m.inv_rest, m.volume, m.mu, m.lam], outputs=[out])
        return out

    def _operator(self, x, y, cm: float, ck: float) -> None:
        m = self.model
        kx = self.stiffness(x, self._tmp["kx"])
        wp.launch(_combine, dim=m.total_nodes, device=m.device, inputs=[x, kx, m.node_mass, m.node_pinned, cm, ck],
                  outputs=[y])

    def _dot(self, a, b, out) -> wp.array:
        m = self.model
        out.zero_()
        wp.launch(_instance_dot, dim=m.total_nodes, device=m.device, inputs=[a, b, m.node_instance], outputs=[out])
        return out

    def solve(self, rhs: wp.array, x: wp.array, cm: float, ck: float) -> None:
        """(cm M + ck K) x = rhs on the free nodes (x holds the first guess; pinned rows are zero)."""
        m, t, d = self.model, self._tmp, self._dots
        dev, n = m.device, m.total_nodes
        p = m.params
        # The tolerance is relative to the (free) right-hand side, so a warm start does not tighten it.
        t["ap"].zero_()
        wp.launch(_residual, dim=n, device=dev, inputs=[rhs, t["ap"], m.node_pinned], outputs=[t["r"]])
        r0 = np.maximum(self._dot(t["r"], t["r"], d["rr"]).numpy(), 1e-300)
        self._operator(x, t["ap"], cm, ck)
        wp.launch(_residual, dim=n, device=dev, inputs=[rhs, t["ap"], m.node_pinned], outputs=[t["r"]])
        wp.launch(_precondition, dim=n, device=dev, inputs=[t["r"], m.node_mass, self.diag, m.node_pinned, cm, ck],
                  outputs=[t["z"]])
        wp.copy(t["p"], t["z"])
        self._dot(t["r"], t["z"], d["rz"])
        it = 0
        while it < p.cg_iterations:
            for _ in range(8):
                self._operator(t["p"], t["ap"], cm, ck)
                self._dot(t["p"], t["ap"], d["pap"])
                wp.launch(_step_x_r, dim=n, device=dev, inputs=[x, t["r"], t["p"], t["ap"], m.node_instance, d["rz"],
                                                                d["pap"]])
                wp.launch(_precondition, dim=n, device=dev,
                          inputs=[t["r"], m.node_mass, self.diag, m.node_pinned, cm, ck], outputs=[t["z"]])
                self._dot(t["r"], t["z"], d["rz_new"])
                wp.launch(_step_p, dim=n, device=dev, inputs=[t["p"], t["z"], m.node_instance, d["rz_new"], d["rz"]])
                wp.copy(d["rz"], d["rz_new"])
                it += 1
            if np.all(self._dot(t["r"], t["r"], d["rr"]).numpy() <= p.cg_tolerance ** 2 * r0):
                break
        else:
            self.cg_capped += 1
        self.cg_iterations = it

    # -- integration --------------------------------------------------------------------------------
    def static(self, f: wp.array) -> None:
        """u = the static equilibrium K u = f (free nodes); v = a = 0."""
        self.solve(f, self.u, 0.0, 1.0)
        self.v.zero_()
        self.a.zero_()

    def step(self, f: wp.array, h: float) -> None:
        """One Newmark step of h [s] to the force f [N] (N*Nn,) vec3 at the step's end (module doc)."""
        m, t = self.model, self._tmp
        a_m, a_k = m.params.damping_mass, m.params.damping_stiffness
        n, dev = m.total_nodes, m.device
        wp.launch(_predict, dim=n, device=dev, inputs=[self.u, self.v, self.a, h, a_k],
                  outputs=[t["u_pred"], t["v_pred"], t["probe"]])
        k_probe = self.stiffness(t["probe"], t["kx"])
        wp.launch(_step_rhs, dim=n, device=dev, inputs=[f, t["v_pred"], k_probe, m.node_mass, m.node_pinned, a_m],
                  outputs=[t["rhs"]])
        self.solve(t["rhs"], self.a, 1.0 + 0.5 * h * a_m, 0.5 * h * a_k + 0.25 * h * h)
        wp.launch(_correct, dim=n, device=dev, inputs=[t["u_pred"], t["v_pred"], self.a, h], outputs=[self.u, self.v])

    def energy(self, f: np.ndarray | None = None) -> np.ndarray:
        """Per instance [J]: 1/2 v^T M v + 1/2 u^T K u - f^T u (f: a constant force (N*Nn, 3), or None)."""
        m = self.model
        ku = self.stiffness(self.u, self._tmp["kx"]).numpy().astype(np.float64)
        u, v = self.u.numpy().astype(np.float64), self.v.numpy().astype(np.float64)
        mass = m.node_mass.numpy().astype(np.float64)
        per = 0.5 * mass * np.sum(v * v, axis=1) + 0.5 * np.sum(u * ku, axis=1)
        if f is not None:
            per -= np.sum(np.asarray(f, dtype=np.float64) * u, axis=1)
        return per.reshape(m.num_instances, -1).sum(axis=1)
