"""Block-Jacobi preconditioned conjugate gradients on the model's 3x3-block BSR Hessian.

The Newton system of one solver step, H dx = -g, is solved by PCG with the inverse of each
vertex's 3x3 diagonal block as preconditioner (``warp.optim.linear``'s "diag" preconditioner
inverts scalar diagonals only; the 3x3 blocks also capture the anisotropy of stretch and contact).

Pinned (kinematic) vertices are removed from the system in place before the solve: their rows and
columns are zeroed, their diagonal block set to the identity and their right-hand side to zero,
so their update is exactly 0 and the free vertices do not feel them through H.

No host synchronisation happens inside :meth:`BlockJacobiPCG.solve`: it launches a fixed
``max_iterations`` sequence of kernels and each kernel first reads an on-device ``done`` flag, set
when the preconditioned residual r.z has fallen below tol^2 times its initial value, and returns at
once after that. The sequence is therefore capturable in a CUDA graph; the iteration count and
final residual stay on the device until :meth:`BlockJacobiPCG.iterations` /
:meth:`BlockJacobiPCG.residual_ratio` read them.

Per iteration: (1) q = H p fused with the reduction p.q, (2) x += alpha p, r -= alpha q,
z = M^-1 r fused with r.z, (3) one thread: beta, convergence test, counters, (4) p = z + beta p.
Reductions are atomic adds into one scalar; on a GPU with large systems a tiled reduction would
cut the contention (to be measured).
"""


import functools
from types import SimpleNamespace

import warp as wp

from simgen.sim.energies._common import module_name, scalar_types

__all__ = ["BlockJacobiPCG", "pcg_kernels"]


@functools.cache
def pcg_kernels(scalar) -> SimpleNamespace:
    """The PCG kernels for one scalar type (module ``simgen.sim.linear.<scalar>``)."""
    T = scalar_types(scalar)
    vec3, mat33 = T.vec3, T.mat33
    mod = module_name(__name__, scalar)
    zero = scalar(0.0)

    @wp.kernel(enable_backward=False, module=mod)
    def constrain(
        rows: wp.array(dtype=wp.int32),
        columns: wp.array(dtype=wp.int32),
        pinned: wp.array(dtype=wp.int32),
        values: wp.array(dtype=mat33),
    ):
        # Pinned rows/columns: zero off-diagonal blocks, identity diagonal block.
        k = wp.tid()
        i = rows[k]
        j = columns[k]
        if pinned[i] != 0 or pinned[j] != 0:
            if i == j:
                values[k] = wp.identity(n=3, dtype=scalar)
            else:
                values[k] = mat33()

    @wp.kernel(enable_backward=False, module=mod)
    def setup(
        values: wp.array(dtype=mat33),
        diag_slots: wp.array(dtype=wp.int32),
        pinned: wp.array(dtype=wp.int32),
        rhs: wp.array(dtype=vec3),
        x: wp.array(dtype=vec3),
        inv_diag: wp.array(dtype=mat33),
        r: wp.array(dtype=vec3),
        z: wp.array(dtype=vec3),
        p: wp.array(dtype=vec3),
        rz: wp.array(dtype=scalar),
    ):
        # Start from x = 0: r = b (zero at pinned vertices), z = D^-1 r, p = z, rz = r.z.
        i = wp.tid()
        d = values[diag_slots[i]]
        dinv = wp.identity(n=3, dtype=scalar)
        if pinned[i] == 0:
            # The assembled diagonal blocks are SPD (mass + PSD-projected terms); a block that is
            # numerically singular (zero mass would be a model error) falls back to the identity.
            det = wp.determinant(d)
            scale = wp.trace(d)
            if det > scalar(1.0e-30) * scale * scale * scale and scale > zero:
                dinv = wp.inverse(d)
        inv_diag[i] = dinv
        b = rhs[i]
        if pinned[i] != 0:
            b = vec3()
        x[i] = vec3()
        r[i] = b
        zi = dinv * b
        z[i] = zi
        p[i] = zi
        wp.atomic_add(rz, 0, wp.dot(b, zi))

    @wp.kernel(enable_backward=False, module=mod)
    def start(
        rz: wp.array(dtype=scalar),
        rz0: wp.array(dtype=scalar),
        done: wp.array(dtype=wp.int32),
        iterations: wp.array(dtype=wp.int32),
        pq: wp.array(dtype=scalar),
        rz_new: wp.array(dtype=scalar),
    ):
        rz0[0] = rz[0]
        iterations[0] = 0
        pq[0] = zero
        rz_new[0] = zero
        done[0] = 0
        if not (rz[0] > zero):
            done[0] = 1  # zero right-hand side: x = 0 is exact

    @wp.kernel(enable_backward=False, module=mod)
    def spmv_dot(
        offsets: wp.array(dtype=wp.int32),
        columns: wp.array(dtype=wp.int32),
        values: wp.array(dtype=mat33),
        p: wp.array(dtype=vec3),
        q: wp.array(dtype=vec3),
        pq: wp.array(dtype=scalar),
        done: wp.array(dtype=wp.int32),
    ):
        i = wp.tid()
        if done[0] != 0:
            return
        acc = vec3()
        for k in range(offsets[i], offsets[i + 1]):
            acc += values[k] * p[columns[k]]
        q[i] = acc
        wp.atomic_add(pq, 0, wp.dot(p[i], acc))

    @wp.kernel(enable_backward=False, module=mod)
    def update_xr(
        p: wp.array(dtype=vec3),
        q: wp.array(dtype=vec3),
        inv_diag: wp.array(dtype=mat33),
        rz: wp.array(dtype=scalar),
        pq: wp.array(dtype=scalar),
        x: wp.array(dtype=vec3),
        r: wp.array(dtype=vec3),
        z: wp.array(dtype=vec3),
        rz_new: wp.array(dtype=scalar),
        done: wp.array(dtype=wp.int32),
    ):
        i = wp.tid()
        if done[0] != 0:
            return
        alpha = zero
        if pq[0] > zero:
            alpha = rz[0] / pq[0]
        x[i] = x[i] + alpha * p[i]
        ri = r[i] - alpha * q[i]
        r[i] = ri
        zi = inv_diag[i] * ri
        z[i] = zi
        wp.atomic_add(rz_new, 0, wp.dot(ri, zi))

    @wp.kernel(enable_backward=False, module=mod)
    def control(
        rz: wp.array(dtype=scalar),
        rz0: wp.array(dtype=scalar),
        pq: wp.array(dtype=scalar),
        rz_new: wp.array(dtype=scalar),
        beta: wp.array(dtype=scalar),
        tol2: scalar,
        done: wp.array(dtype=wp.int32),
        iterations: wp.array(dtype=wp.int32),
    ):
        if done[0] != 0:
            return
        iterations[0] = iterations[0] + 1
        # A non-positive curvature p.Hp means H is not SPD along p (should not happen with
        # PSD-projected terms plus the mass); stop rather than divide by it.
        if not (pq[0] > zero) or rz_new[0] <= tol2 * rz0[0]:
            done[0] = 1
        b = zero
        if rz[0] > zero:
            b = rz_new[0] / rz[0]
        beta[0] = b
        rz[0] = rz_new[0]
        pq[0] = zero
        rz_new[0] = zero

    @wp.kernel(enable_backward=False, module=mod)
    def update_p(
        z: wp.array(dtype=vec3),
        beta: wp.array(dtype=scalar),
        p: wp.array(dtype=vec3),
        done: wp.array(dtype=wp.int32),
    ):
        i = wp.tid()
        if done[0] != 0:
            return
        p[i] = z[i] + beta[0] * p[i]

    return SimpleNamespace(constrain=constrain, setup=setup, start=start, spmv_dot=spmv_dot, update_xr=update_xr,
                           control=control, update_p=update_p)


class BlockJacobiPCG:
    """Preallocated block-Jacobi PCG for one :class:`~simgen.sim.model.ClothModel`.

    model: the cloth model (its BSR pattern, diagonal slots and pinned flags are used).
    max_iterations: the fixed number of iterations launched per solve (work stops on the device
      once converged). tolerance: relative tolerance on the preconditioned residual,
      sqrt(r.M^-1 r / r0.M^-1 r0) <= tolerance.

    All arrays are allocated here, so :meth:`solve` allocates nothing (graph-capture safe).
    """

    def __init__(self, model, *, max_iterations: int = 50, tolerance: float = 1.0e-3) -> None:
        if int(max_iterations) < 1:
            raise ValueError(f"max_iterations must be >= 1, got {max_iterations}")
        if not tolerance >= 0:
            raise ValueError(f"tolerance must be >= 0, got {tolerance}")
        self.model = model
        self.max_iterations = int(max_iterations)
        self.tolerance = float(tolerance)
        self.kernels = pcg_kernels(model.scalar)
        T = scalar_types(model.scalar)
        n, dev = model.num_vertices, model.device
        self.inv_diag = wp.zeros(n, dtype=T.mat33, device=dev)
        self.r = wp.zeros(n, dtype=T.vec3, device=dev)
        self.z = wp.zeros(n, dtype=T.vec3, device=dev)
        self.p = wp.zeros(n, dtype=T.vec3, device=dev)
        self.q = wp.zeros(n, dtype=T.vec3, device=dev)
        # Device scalars: r.z, initial r.z, p.Hp, new r.z, beta; done flag and iteration count.
        self._rz = wp.zeros(1, dtype=T.scalar, device=dev)
        self._rz0 = wp.zeros(1, dtype=T.scalar, device=dev)
        self._pq = wp.zeros(1, dtype=T.scalar, device=dev)
        self._rz_new = wp.zeros(1, dtype=T.scalar, device=dev)
        self._beta = wp.zeros(1, dtype=T.scalar, device=dev)
        self._done = wp.zeros(1, dtype=wp.int32, device=dev)
        self._iterations = wp.zeros(1, dtype=wp.int32, device=dev)

    def load(self) -> None:
        """Compile (or fetch from Warp's cache) the kernels; call before capturing a graph."""
        wp.load_module(module_name(__name__, self.model.scalar), device=self.model.device)

    def apply_constraints(self, hessian) -> None:
        """Zero the rows and columns of pinned vertices in ``hessian`` (BsrMatrix or its values),
        with identity diagonal blocks, in place."""
        m = self.model
        values = getattr(hessian, "values", hessian)
        wp.launch(self.kernels.constrain, dim=m.nnz, device=m.device,
                  inputs=[m.bsr_rows, m.bsr_columns, m.vertex_pinned, values])

    def solve(self, hessian, rhs, x) -> None:
        """Solve hessian x = rhs approximately; x is overwritten (the iteration starts at 0).

        hessian: the model's BsrMatrix (or its (nnz,) mat33 values), SPD after
          :meth:`apply_constraints` (call that first when the model has pinned vertices).
        rhs: (V,) vec3, e.g. the negative gradient [J/m]; pinned entries are treated as 0.
        x: (V,) vec3 output, e.g. the Newton step [m]; exactly 0 at pinned vertices.
        """
        m, k = self.model, self.kernels
        n, dev = m.num_vertices, m.device
        values = getattr(hessian, "values", hessian)
        self._rz.zero_()
        wp.launch(k.setup, dim=n, device=dev, inputs=[
            values, m.diag_slots, m.vertex_pinned, rhs, x, self.inv_diag, self.r, self.z, self.p, self._rz])
        wp.launch(k.start, dim=1, device=dev, inputs=[
            self._rz, self._rz0, self._done, self._iterations, self._pq, self._rz_new])
        tol2 = self.tolerance * self.tolerance
        for _ in range(self.max_iterations):
            wp.launch(k.spmv_dot, dim=n, device=dev, inputs=[
                m.bsr_offsets, m.bsr_columns, values, self.p, self.q, self._pq, self._done])
            wp.launch(k.update_xr, dim=n, device=dev, inputs=[
                self.p, self.q, self.inv_diag, self._rz, self._pq, x, self.r, self.z, self._rz_new, self._done])
            wp.launch(k.control, dim=1, device=dev, inputs=[
                self._rz, self._rz0, self._pq, self._rz_new, self._beta, tol2, self._done, self._iterations])
            wp.launch(k.update_p, dim=n, device=dev, inputs=[self.z, self._beta, self.p, self._done])

    @property
    def iteration_counter(self) -> wp.array:
        """(1,) int32 device array: iterations of the last solve (read without a host sync)."""
        return self._iterations

    def iterations(self) -> int:
        """Iterations the last solve took (host sync)."""
        return int(self._iterations.numpy()[0])

    def residual_ratio(self) -> float:
        """sqrt(r.M^-1 r / r0.M^-1 r0) at the end of the last solve (host sync)."""
        rz, rz0 = float(self._rz.numpy()[0]), float(self._rz0.numpy()[0])
        return (max(rz, 0.0) / rz0) ** 0.5 if rz0 > 0 else 0.0
