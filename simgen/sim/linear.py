"""Block-Jacobi preconditioned conjugate gradients on the model's 3x3-block BSR Hessian.

The Newton system of one solver step, H dx = -g, is solved by PCG with the inverse of each
vertex's 3x3 diagonal block as preconditioner (``warp.optim.linear``'s "diag" preconditioner
inverts scalar diagonals only; the 3x3 blocks also capture the anisotropy of stretch and contact).

Pinned (kinematic) vertices are removed from the system in place before the solve: their rows and
columns are zeroed, their diagonal block set to the identity and their right-hand side to zero,
so their update is exactly 0 and the free vertices do not feel them through H.

A solve starts from 0 or from a guess (a warm start: r = b - H x0 by one more sliced-ELL product).
The iteration loop is ``warp.capture_while`` on an on-device "running" flag, cleared once every
instance's preconditioned residual r.z has fallen below tol^2 times the right-hand side's b.M^-1 b
(with no guess, the initial residual's) or after
``max_iterations``: inside a CUDA graph it is a conditional node, so a captured solve launches only
the iterations it needs and reads nothing back; outside a graph it reads the flag once per
iteration. With ``dynamic=False`` the solve launches a fixed ``max_iterations`` sequence instead,
every kernel returning at once after convergence. The iteration count and final residual stay on
the device until :meth:`BlockJacobiPCG.iterations` / :meth:`BlockJacobiPCG.residual_ratio` read
them.

Batched models: the Hessian is block diagonal over instances, so every instance runs its own CG
(its own alpha, beta, residual and stopping test) inside the same launches; an instance that has
converged, or whose right-hand side is not finite, stops without holding up or poisoning the
others, and every launch returns at once when all instances are done.

Per iteration, three launches: (1) p = z + beta p and q = H p computed as H z + beta q (q holds
H p of the previous iteration, so no separate pass updates p before the product), fused with the
per-instance reduction p.q, (2) x += alpha p, r -= alpha q, z = M^-1 r fused with r.z, (3) one
block, a thread per instance: each instance's beta and convergence test, then (a tile sum of the
instances still running) the iteration count and the all-done flag.
The recurrence for q is exact in exact arithmetic (H is linear); in float32 it drifts from H p by
round-off only, far below the 1e-3 tolerance the solver uses. Reductions are segmented block
reductions (simgen.sim.warp_toolkit.reduce_funcs): a block of ``REDUCE_BLOCK`` vertices sums
its first instance's share in a tile and adds it with one atomic. Per-vertex atomics into one
scalar per instance serialise on that address (measured in BENCHMARKS.md).

The product reads a sliced-ELL copy of H, gathered once per solve: slices of ``ELL_SLICE`` rows
(a warp) padded to their longest row with zero blocks in the row's own column and stored slot by
slot, so a warp reads adjacent blocks; read row by row from the BSR, its 32 loads are a row apart
and the product runs far below the memory bandwidth (BENCHMARKS.md).
"""


import functools
from types import SimpleNamespace

import numpy as np
import warp as wp

from simgen.sim.warp_toolkit import REDUCE_BLOCK, module_name, reduce_block, reduce_funcs, scalar_types

__all__ = ["BlockJacobiPCG", "pcg_kernels", "sliced_ell_layout", "REDUCE_BLOCK", "ELL_SLICE"]

# Rows per slice of the sliced-ELL matrix: one CUDA warp, whose loads of one slot step coalesce.
ELL_SLICE = 32


@functools.cache
def pcg_kernels(scalar) -> SimpleNamespace:
    """The PCG kernels for one scalar type (module ``simgen.sim.linear.<scalar>``)."""
    T = scalar_types(scalar)
    vec3, mat33 = T.vec3, T.mat33
    mod = module_name(__name__, scalar)
    zero = scalar(0.0)
    block_add = reduce_funcs(scalar).block_add

    @wp.func(module=mod)
    def ell_row(slice_starts: wp.array(dtype=wp.int32), slice_widths: wp.array(dtype=wp.int32),
                ell_columns: wp.array(dtype=wp.int32), ell_values: wp.array(dtype=mat33), v: wp.array(dtype=vec3),
                i: int):
        # Row i of H v from the sliced-ELL copy of H.
        acc = vec3()
        s = i // ELL_SLICE
        first = slice_starts[s] + i % ELL_SLICE
        for j in range(slice_widths[s]):
            e = first + j * ELL_SLICE
            acc += ell_values[e] * v[ell_columns[e]]
        return acc

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
    def gather_ell(values: wp.array(dtype=mat33), ell_source: wp.array(dtype=wp.int32),
                   ell_values: wp.array(dtype=mat33)):
        # One thread per ELL entry: the writes coalesce (the strided reads happen once per solve).
        e = wp.tid()
        k = ell_source[e]
        if k >= 0:
            ell_values[e] = values[k]
        else:
            ell_values[e] = mat33()

    @wp.kernel(enable_backward=False, module=mod)
    def setup(
        values: wp.array(dtype=mat33),
        diag_slots: wp.array(dtype=wp.int32),
        pinned: wp.array(dtype=wp.int32),
        vertex_instance: wp.array(dtype=wp.int32),
        rhs: wp.array(dtype=vec3),
        x: wp.array(dtype=vec3),
        inv_diag: wp.array(dtype=mat33),
        r: wp.array(dtype=vec3),
        z: wp.array(dtype=vec3),
        p: wp.array(dtype=vec3),
        q: wp.array(dtype=vec3),
        rz: wp.array(dtype=scalar),
        n: int,
    ):
        # Start from x = 0: r = b (zero at pinned vertices), z = D^-1 r, p = q = 0 (the first
        # iteration's beta is 0, so it makes p = z), rz = r.z per instance.
        block, lane = wp.tid()
        i = block * wp.block_dim() + lane
        value = zero
        if i < n:
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
            p[i] = vec3()
            q[i] = vec3()
            value = wp.dot(b, zi)
        # One call site for every thread of the block: the tile sum synchronises the block.
        block_add(rz, vertex_instance, block, lane, i, n, value)

    @wp.kernel(enable_backward=False, module=mod)
    def warm_residual(
        slice_starts: wp.array(dtype=wp.int32),
        slice_widths: wp.array(dtype=wp.int32),
        ell_columns: wp.array(dtype=wp.int32),
        ell_values: wp.array(dtype=mat33),
        vertex_instance: wp.array(dtype=wp.int32),
        pinned: wp.array(dtype=wp.int32),
        rhs: wp.array(dtype=vec3),
        guess: wp.array(dtype=vec3),
        inv_diag: wp.array(dtype=mat33),
        x: wp.array(dtype=vec3),
        r: wp.array(dtype=vec3),
        z: wp.array(dtype=vec3),
        rz: wp.array(dtype=scalar),
        done: wp.array(dtype=wp.int32),
        n: int,
    ):
        # Start from x = guess (0 at pinned vertices): r = b - H x, z = D^-1 r, rz = r.z per instance.
        # An instance already done (a zero right-hand side) keeps x = 0.
        block, lane = wp.tid()
        i = block * wp.block_dim() + lane
        value = zero
        if i < n and done[vertex_instance[i]] == 0:
            g = guess[i]
            b = rhs[i]
            if pinned[i] != 0:
                g = vec3()
                b = vec3()
            # Pinned columns are zero after apply_constraints, so a pinned entry of the guess adds nothing.
            ri = b - ell_row(slice_starts, slice_widths, ell_columns, ell_values, guess, i)
            if pinned[i] != 0:
                ri = vec3()
            x[i] = g
            r[i] = ri
            zi = inv_diag[i] * ri
            z[i] = zi
            value = wp.dot(ri, zi)
        block_add(rz, vertex_instance, block, lane, i, n, value)

    @wp.kernel(enable_backward=False, module=mod)
    def warm_check(rz: wp.array(dtype=scalar), rz0: wp.array(dtype=scalar), tol2: scalar,
                   done: wp.array(dtype=wp.int32)):
        # An instance whose guess already meets the tolerance (relative to its right-hand side) is done.
        k = wp.tid()
        if rz[k] <= tol2 * rz0[k]:
            done[k] = 1

    @wp.kernel(enable_backward=False, module=mod)
    def start(
        rz: wp.array(dtype=scalar),
        rz0: wp.array(dtype=scalar),
        done: wp.array(dtype=wp.int32),
        pq: wp.array(dtype=scalar),
        rz_new: wp.array(dtype=scalar),
        beta: wp.array(dtype=scalar),
    ):
        k = wp.tid()
        rz0[k] = rz[k]
        pq[k] = zero
        rz_new[k] = zero
        beta[k] = zero  # the first direction is p = z
        done[k] = 0
        if not (rz[k] > zero):
            done[k] = 1  # zero right-hand side (or a non-finite one): x = 0 is the answer

    @wp.kernel(enable_backward=False, module=mod)
    def start_all(done: wp.array(dtype=wp.int32), num_instances: int, iterations: wp.array(dtype=wp.int32),
                  all_done: wp.array(dtype=wp.int32), running: wp.array(dtype=wp.int32)):
        iterations[0] = 0
        flag = int(1)
        for k in range(num_instances):
            if done[k] == 0:
                flag = 0
        all_done[0] = flag
        running[0] = 1 - flag

    @wp.kernel(enable_backward=False, module=mod)
    def direction_spmv_dot(
        slice_starts: wp.array(dtype=wp.int32),
        slice_widths: wp.array(dtype=wp.int32),
        ell_columns: wp.array(dtype=wp.int32),
        ell_values: wp.array(dtype=mat33),
        vertex_instance: wp.array(dtype=wp.int32),
        z: wp.array(dtype=vec3),
        beta: wp.array(dtype=scalar),
        p: wp.array(dtype=vec3),
        q: wp.array(dtype=vec3),
        pq: wp.array(dtype=scalar),
        done: wp.array(dtype=wp.int32),
        all_done: wp.array(dtype=wp.int32),
        n: int,
    ):
        # p <- z + beta p, q <- H z + beta q (= H p): each row reads only z of its neighbours.
        if all_done[0] != 0:
            return  # uniform over the block, so no thread misses the tile sum below
        block, lane = wp.tid()
        i = block * wp.block_dim() + lane
        value = zero
        if i < n:
            inst = vertex_instance[i]
            if done[inst] == 0:
                acc = ell_row(slice_starts, slice_widths, ell_columns, ell_values, z, i)
                b = beta[inst]
                pi = z[i] + b * p[i]
                qi = acc + b * q[i]
                p[i] = pi
                q[i] = qi
                value = wp.dot(pi, qi)
        block_add(pq, vertex_instance, block, lane, i, n, value)

    @wp.kernel(enable_backward=False, module=mod)
    def update_xr(
        vertex_instance: wp.array(dtype=wp.int32),
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
        all_done: wp.array(dtype=wp.int32),
        n: int,
    ):
        if all_done[0] != 0:
            return
        block, lane = wp.tid()
        i = block * wp.block_dim() + lane
        value = zero
        if i < n:
            inst = vertex_instance[i]
            if done[inst] == 0:
                alpha = zero
                if pq[inst] > zero:
                    alpha = rz[inst] / pq[inst]
                x[i] = x[i] + alpha * p[i]
                ri = r[i] - alpha * q[i]
                r[i] = ri
                zi = inv_diag[i] * ri
                z[i] = zi
                value = wp.dot(ri, zi)
        block_add(rz_new, vertex_instance, block, lane, i, n, value)

    @wp.kernel(enable_backward=False, module=mod)
    def control(
        rz: wp.array(dtype=scalar),
        rz0: wp.array(dtype=scalar),
        pq: wp.array(dtype=scalar),
        rz_new: wp.array(dtype=scalar),
        beta: wp.array(dtype=scalar),
        tol2: scalar,
        num_instances: int,
        max_iterations: int,
        done: wp.array(dtype=wp.int32),
        iterations: wp.array(dtype=wp.int32),
        all_done: wp.array(dtype=wp.int32),
        running: wp.array(dtype=wp.int32),
    ):
        # One block, a thread per instance (strided): each instance's CG runs and stops on its own
        # residual; iterations = the most any instance ran; all_done lets every later launch return
        # at once; running (the loop's condition) also stops at max_iterations. One thread looping
        # over the instances waited on a chain of dependent loads per instance (BENCHMARKS.md).
        block, lane = wp.tid()
        if all_done[0] != 0:
            if lane == 0:
                running[0] = 0
            return  # uniform over the block, so no thread misses the tile sum below
        active = int(0)
        k = lane
        while k < num_instances:
            if done[k] == 0:
                # A non-positive (or non-finite) curvature p.Hp means H is not SPD along p (should
                # not happen with PSD-projected terms plus the mass); stop rather than divide by it.
                if not (pq[k] > zero) or rz_new[k] <= tol2 * rz0[k]:
                    done[k] = 1
                b = zero
                if rz[k] > zero:
                    b = rz_new[k] / rz[k]
                beta[k] = b
                rz[k] = rz_new[k]
                pq[k] = zero
                rz_new[k] = zero
                if done[k] == 0:
                    active += 1
            k += wp.block_dim()
        left = wp.tile_sum(wp.tile(active))
        if lane == 0:
            count = iterations[0] + 1
            iterations[0] = count
            flag = int(0)
            if left[0] == 0:
                flag = 1
            all_done[0] = flag
            running[0] = 0
            if flag == 0 and count < max_iterations:
                running[0] = 1

    return SimpleNamespace(constrain=constrain, gather_ell=gather_ell, setup=setup, warm_residual=warm_residual,
                           warm_check=warm_check, start=start, start_all=start_all,
                           direction_spmv_dot=direction_spmv_dot, update_xr=update_xr, control=control)


class BlockJacobiPCG:
    """Preallocated block-Jacobi PCG for one :class:`~simgen.sim.model.ClothModel`.

    model: the cloth model (its BSR pattern, diagonal slots and pinned flags are used).
    max_iterations: the most iterations per solve. tolerance: relative tolerance on the
      preconditioned residual, sqrt(r.M^-1 r / b.M^-1 b) <= tolerance (b: the right-hand side; with
      no guess, the initial residual).
    dynamic: loop with ``warp.capture_while`` until converged (a conditional node in a CUDA graph);
      False launches a fixed ``max_iterations`` sequence (work stops on the device once converged).

    All arrays are allocated here, so :meth:`solve` allocates nothing (graph-capture safe), among them
    the sliced-ELL copy of the Hessian: ``slice_starts``, ``slice_widths``, ``ell_columns`` and
    ``ell_source`` (:func:`sliced_ell_layout`) and ``ell_values``, which each solve refills.
    """

    def __init__(self, model, *, max_iterations: int = 50, tolerance: float = 1.0e-3, dynamic: bool = True) -> None:
        if int(max_iterations) < 1:
            raise ValueError(f"max_iterations must be >= 1, got {max_iterations}")
        if not tolerance >= 0:
            raise ValueError(f"tolerance must be >= 0, got {tolerance}")
        self.model = model
        self.max_iterations = int(max_iterations)
        self.tolerance = float(tolerance)
        self.dynamic = bool(dynamic)
        self.kernels = pcg_kernels(model.scalar)
        T = scalar_types(model.scalar)
        n, dev = model.num_vertices, model.device
        self.inv_diag = wp.zeros(n, dtype=T.mat33, device=dev)
        self.r = wp.zeros(n, dtype=T.vec3, device=dev)
        self.z = wp.zeros(n, dtype=T.vec3, device=dev)
        self.p = wp.zeros(n, dtype=T.vec3, device=dev)
        self.q = wp.zeros(n, dtype=T.vec3, device=dev)
        # Per instance on the device: r.z, initial r.z, p.Hp, new r.z, beta, done flag; plus the
        # iteration count (the most any instance ran) and an all-done flag.
        ni = model.num_instances
        self._rz = wp.zeros(ni, dtype=T.scalar, device=dev)
        self._rz0 = wp.zeros(ni, dtype=T.scalar, device=dev)
        self._pq = wp.zeros(ni, dtype=T.scalar, device=dev)
        self._rz_new = wp.zeros(ni, dtype=T.scalar, device=dev)
        self._beta = wp.zeros(ni, dtype=T.scalar, device=dev)
        self._done = wp.zeros(ni, dtype=wp.int32, device=dev)
        self._all_done = wp.zeros(1, dtype=wp.int32, device=dev)
        self._iterations = wp.zeros(1, dtype=wp.int32, device=dev)
        self._running = wp.zeros(1, dtype=wp.int32, device=dev)
        self._block = reduce_block(dev)
        self._blocks = (n + self._block - 1) // self._block
        self._control_block = _control_block(dev, ni)
        pattern = model.pattern
        slice_starts, slice_widths, ell_columns, ell_source = sliced_ell_layout(pattern.offsets, pattern.columns)
        self.slice_starts = wp.array(slice_starts, dtype=wp.int32, device=dev)
        self.slice_widths = wp.array(slice_widths, dtype=wp.int32, device=dev)
        self.ell_columns = wp.array(ell_columns, dtype=wp.int32, device=dev)
        self.ell_source = wp.array(ell_source, dtype=wp.int32, device=dev)
        self.ell_values = wp.zeros(len(ell_source), dtype=T.mat33, device=dev)

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

    def solve(self, hessian, rhs, x, guess=None) -> None:
        """Solve hessian x = rhs approximately; x is overwritten.

        hessian: the model's BsrMatrix (or its (nnz,) mat33 values), SPD after
          :meth:`apply_constraints` (call that first when the model has pinned vertices).
        rhs: (V,) vec3, e.g. the negative gradient [J/m]; pinned entries are treated as 0.
        x: (V,) vec3 output, e.g. the Newton step [m]; exactly 0 at pinned vertices.
        guess: (V,) vec3 where the iteration starts (a warm start), or None for 0. The stopping test
          is relative to the right-hand side either way: r.M^-1 r <= tolerance^2 b.M^-1 b.
        """
        m, k = self.model, self.kernels
        n, dev = m.num_vertices, m.device
        values = getattr(hessian, "values", hessian)
        ni, vi = m.num_instances, m.vertex_instance
        self._rz.zero_()
        wp.launch(k.gather_ell, dim=len(self.ell_values), device=dev,
                  inputs=[values, self.ell_source, self.ell_values])
        wp.launch_tiled(k.setup, dim=[self._blocks], block_dim=self._block, device=dev, inputs=[
            values, m.diag_slots, m.vertex_pinned, vi, rhs, x, self.inv_diag, self.r, self.z, self.p, self.q,
            self._rz, n])
        wp.launch(k.start, dim=ni, device=dev,
                  inputs=[self._rz, self._rz0, self._done, self._pq, self._rz_new, self._beta])
        if guess is not None:
            self._rz.zero_()
            wp.launch_tiled(k.warm_residual, dim=[self._blocks], block_dim=self._block, device=dev, inputs=[
                self.slice_starts, self.slice_widths, self.ell_columns, self.ell_values, vi, m.vertex_pinned, rhs,
                guess, self.inv_diag, x, self.r, self.z, self._rz, self._done, n])
            wp.launch(k.warm_check, dim=ni, device=dev,
                      inputs=[self._rz, self._rz0, self.tolerance * self.tolerance, self._done])
        wp.launch(k.start_all, dim=1, device=dev,
                  inputs=[self._done, ni, self._iterations, self._all_done, self._running])
        if self.dynamic:
            wp.capture_while(self._running, self._iteration, x=x)
        else:
            for _ in range(self.max_iterations):
                self._iteration(x=x)

    def _iteration(self, x) -> None:
        m, k = self.model, self.kernels
        n, dev, vi = m.num_vertices, m.device, m.vertex_instance
        wp.launch_tiled(k.direction_spmv_dot, dim=[self._blocks], block_dim=self._block, device=dev, inputs=[
            self.slice_starts, self.slice_widths, self.ell_columns, self.ell_values, vi, self.z, self._beta, self.p,
            self.q, self._pq, self._done, self._all_done, n])
        wp.launch_tiled(k.update_xr, dim=[self._blocks], block_dim=self._block, device=dev, inputs=[
            vi, self.p, self.q, self.inv_diag, self._rz, self._pq, x, self.r, self.z, self._rz_new, self._done,
            self._all_done, n])
        wp.launch_tiled(k.control, dim=[1], block_dim=self._control_block, device=dev, inputs=[
            self._rz, self._rz0, self._pq, self._rz_new, self._beta, self.tolerance * self.tolerance,
            m.num_instances, self.max_iterations, self._done, self._iterations, self._all_done, self._running])

    @property
    def iteration_counter(self) -> wp.array:
        """(1,) int32 device array: iterations of the last solve (read without a host sync)."""
        return self._iterations

    def iterations(self) -> int:
        """Iterations the last solve took (host sync)."""
        return int(self._iterations.numpy()[0])

    def residual_ratio(self) -> float:
        """The largest per-instance sqrt(r.M^-1 r / b.M^-1 b) at the end of the last solve (host sync)."""
        rz, rz0 = self._rz.numpy().astype(float), self._rz0.numpy().astype(float)
        ratios = [(max(a, 0.0) / b) ** 0.5 if b > 0 else 0.0 for a, b in zip(rz, rz0)]
        return max(ratios)


def _control_block(device, num_instances: int) -> int:
    """Threads of the one-block PCG control launch (more instances are strided). On CUDA the
    reducing kernels' block size: Warp compiles a module once per block size, so this launch needs
    no second variant (which would have to be loaded before a CUDA graph is captured). On the CPU up
    to 4, so the CPU tests run the strided, multi-thread path too."""
    if wp.get_device(device).is_cuda:
        return reduce_block(device)
    return int(min(4, max(1, num_instances)))


def sliced_ell_layout(offsets: np.ndarray, columns: np.ndarray) -> tuple[np.ndarray, ...]:
    """Sliced-ELL layout of a BSR pattern: row offsets ``offsets`` (V+1,), block columns ``columns`` (nnz,).

    Returns int32 (slice_starts, slice_widths, ell_columns, ell_source): per slice of ``ELL_SLICE``
    rows its first entry and its width (longest row); per entry the block's column and BSR slot, or
    for padding the row itself and -1. The j-th block of row i (slice s = i // ELL_SLICE) is entry
    ``slice_starts[s] + j * ELL_SLICE + i % ELL_SLICE``. Rows past V in a partial last slice are never
    read; their entries point at the last row, so every column indexes a vertex.
    """
    offsets = np.asarray(offsets, dtype=np.int64)
    n = len(offsets) - 1
    num_slices = -(-n // ELL_SLICE)
    lengths = np.zeros(num_slices * ELL_SLICE, dtype=np.int64)
    lengths[:n] = np.diff(offsets)
    widths = lengths.reshape(num_slices, ELL_SLICE).max(axis=1)
    starts = np.concatenate([[0], np.cumsum(ELL_SLICE * widths)])
    slot_rows = np.repeat(np.arange(n), lengths[:n])  # the row of each BSR slot
    slot_index = np.arange(offsets[-1]) - offsets[slot_rows]  # its position j within the row
    entry = starts[slot_rows // ELL_SLICE] + slot_index * ELL_SLICE + slot_rows % ELL_SLICE
    ell_source = np.full(starts[-1], -1, dtype=np.int64)
    ell_source[entry] = np.arange(offsets[-1])
    entry_slice = np.repeat(np.arange(num_slices), ELL_SLICE * widths)
    entry_rows = entry_slice * ELL_SLICE + (np.arange(starts[-1]) - starts[entry_slice]) % ELL_SLICE
    ell_columns = np.minimum(entry_rows, n - 1)
    ell_columns[entry] = columns[: offsets[-1]]
    return (starts[:-1].astype(np.int32), widths.astype(np.int32), ell_columns.astype(np.int32),
            ell_source.astype(np.int32))
