"""Where the preset's PCG iterations go: per-solve iterations of the cloth solver, and one Newton
system taken out and solved again in scipy with other preconditioners; prints (and saves) JSON.

    python scripts/cg_profile.py --device cpu --json cg.json

Runs the `thesis-tshirt` preset's solver (with two Newton iterations per substep, as the preset had
them until 2026-11-29 and the numbers in docs/sim.md were taken; block-Jacobi PCG to a
relative preconditioned residual of 1e-3, at most ``cg_iterations`` per Newton iteration) on the
T-shirt and the open body doing ``walk`` with a short start protocol, and records every PCG solve
(iterations, whether it hit the cap, final residual ratio). A system H dx = -g
(pinned rows removed) of a first Newton iteration is then handed to scipy in float64: the same block-Jacobi PCG, run to the
cap's tolerance without a cap; an estimate of the condition number of D^-1 H (D: the 3x3 diagonal
blocks) from its extreme eigenvalues; and PCG with symmetric Gauss-Seidel and with incomplete LU
(scipy's spilu, threshold 1e-4) preconditioners, and the same block-Jacobi PCG started from the
previous substep's first Newton step (a warm start). The system analysed is the last substep's
first Newton iteration (the large step; the second is a correction).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np


def _pcg(A, b, precond, tol: float, x0=None, max_iter: int = 5000) -> tuple[int, np.ndarray]:
    """Preconditioned CG on SPD A (scipy sparse), stopping when r.M^-1 r <= tol^2 r0.M^-1 r0 (the
    solver's test); returns iterations and x."""
    x = np.zeros_like(b) if x0 is None else x0.copy()
    r = b - A @ x
    z = precond(r)
    p = z.copy()
    rz = rz0 = float(r @ z)
    for it in range(1, max_iter + 1):
        q = A @ p
        alpha = rz / float(p @ q)
        x += alpha * p
        r -= alpha * q
        z = precond(r)
        rz_new = float(r @ z)
        if rz_new <= tol * tol * rz0:
            return it, x
        p = z + (rz_new / rz) * p
        rz = rz_new
    return max_iter, x


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--device", default="cpu")
    p.add_argument("--frames", type=int, default=3, help="output frames of walk after the protocol")
    p.add_argument("--garment", default="tshirt", help="garment (the preset's: tshirt)")
    p.add_argument("--cold", action="store_true", help="no warm start (SolverConfig.cg_warm_start = false)")
    p.add_argument("--json")
    a = p.parse_args(argv)

    import scipy.sparse as sp
    import scipy.sparse.linalg as spla
    import warp as wp

    wp.config.quiet = True
    from dataclasses import replace

    from simgen.dataset import load_spec
    from simgen.motion.library import load_motion
    from simgen.motion.ops import trim
    from simgen.sim import simulate
    from simgen.sim.linear import BlockJacobiPCG

    spec = load_spec("thesis-tshirt")
    config = replace(spec.solver_config(), device=a.device, relax_frames=2, ramp_frames=5, rest_frames=2,
                     cuda_graph=False)
    config = replace(config, solver=replace(config.solver, cg_warm_start=not a.cold, newton_iterations=2))
    cap = config.solver.cg_iterations
    solves, systems = [], []
    real = BlockJacobiPCG.solve

    def recorded(self, hessian, rhs, x, guess=None):
        real(self, hessian, rhs, x, guess=guess)
        solves.append((self.iterations(), self.residual_ratio()))
        m = self.model
        values = getattr(hessian, "values", hessian).numpy().astype(np.float64)
        systems[:] = systems[-3:] + [(values, m.bsr_rows.numpy(), m.bsr_columns.numpy(), rhs.numpy().astype(np.float64),
                                      x.numpy().astype(np.float64), m.vertex_pinned.numpy().astype(bool))]

    BlockJacobiPCG.solve = recorded
    t0 = time.perf_counter()
    clip = trim(load_motion("walk"), 1.0, 1.0 + a.frames / 30.0)
    simulate(a.garment, "open", clip, None, config, frames=a.frames)
    wall = time.perf_counter() - t0
    BlockJacobiPCG.solve = real
    its = np.array([s[0] for s in solves])
    ratio = np.array([s[1] for s in solves])

    # With two Newton iterations per substep the solves alternate first, second: the last substep's
    # first (the large step) is systems[-2], the previous substep's first systems[-4].
    (_, _, _, _, x0, pinned), (values, rows, cols, b, _, _) = systems[-4], systems[-2]
    n = len(b)
    # The model's (row, column) block lists as a scalar sparse matrix.
    coo_r = (3 * rows[:, None, None] + np.arange(3)[None, :, None]).repeat(3, axis=2)
    coo_c = (3 * cols[:, None, None] + np.arange(3)[None, None, :]).repeat(3, axis=1)
    A = sp.coo_matrix((values.ravel(), (coo_r.ravel(), coo_c.ravel())), shape=(3 * n, 3 * n)).tocsr()
    free = np.repeat(~pinned, 3)
    idx = np.nonzero(free)[0]
    Af = A[idx][:, idx].tocsc()
    bf = b.reshape(-1)[idx]
    blocks = [np.linalg.inv(A[3 * i:3 * i + 3, 3 * i:3 * i + 3].toarray()) for i in range(n)]
    Dinv = sp.block_diag(blocks, format="csr")[idx][:, idx]
    tol = config.solver.cg_tolerance
    result = {"benchmark": "cg_profile", "date": time.strftime("%Y-%m-%d"), "device": a.device,
              "commit": _commit(), "garment": a.garment, "warm_start": not a.cold, "garment_vertices": int(n), "free_dofs": int(len(idx)), "cap_per_newton_iteration": int(cap),
              "tolerance": tol, "solves": int(len(its)), "sim_wall_s": wall,
              "iterations": {"mean": float(its.mean()), "median": float(np.median(its)), "max": int(its.max()),
                             "share_at_cap": float(np.mean(its >= cap)),
                             "residual_ratio_at_cap_median": float(np.median(ratio[its >= cap])) if np.any(its >= cap)
                             else None}}
    jac = (lambda r: Dinv @ r)
    result["scipy_block_jacobi_uncapped"] = _pcg(Af, bf, jac, tol)[0]
    # Extreme eigenvalues of D^-1/2 A D^-1/2 (symmetric): the spectrum of D^-1 A.
    half = sp.block_diag([np.real(_inv_sqrt(A[3 * i:3 * i + 3, 3 * i:3 * i + 3].toarray())) for i in range(n)],
                         format="csr")[idx][:, idx]
    S = (half @ Af @ half).tocsc()
    lmax = float(spla.eigsh(S, k=1, which="LA", return_eigenvectors=False, tol=1e-3)[0])
    lmin = float(spla.eigsh(S, k=1, sigma=0.0, which="LM", return_eigenvectors=False, tol=1e-3)[0])
    result["condition_block_jacobi"] = lmax / lmin
    result["cg_bound_iterations"] = float(0.5 * np.sqrt(lmax / lmin) * np.log(2.0 / tol))
    L = sp.tril(Af, format="csr")
    Dm = sp.diags(Af.diagonal())
    U = sp.triu(Af, format="csr")

    def sgs(r):
        y = spla.spsolve_triangular(L, r, lower=True)
        return spla.spsolve_triangular(U, Dm @ y, lower=False)

    result["scipy_symmetric_gauss_seidel"] = _pcg(Af, bf, sgs, tol)[0]
    # Incomplete LU with threshold (scipy's defaults: drop 1e-4, fill up to 10x): a strong,
    # serial preconditioner, to bound what a better one can gain.
    ilu = spla.spilu(Af)
    result["scipy_ilut"] = _pcg(Af, bf, ilu.solve, tol)[0]
    # Warm start: the previous substep's first Newton step as the first guess of this one.
    prev = x0.reshape(-1)[idx]
    result["scipy_block_jacobi_warm_start"] = _pcg(Af, bf, jac, tol, x0=prev)[0]
    text = json.dumps(result, indent=2)
    print(text)
    if a.json:
        Path(a.json).write_text(text + "\n")
    return 0


def _commit() -> str:
    import os
    import subprocess

    if os.environ.get("SIMGEN_COMMIT"):
        return os.environ["SIMGEN_COMMIT"]
    try:
        return subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=Path(__file__).resolve().parents[1],
                              capture_output=True, text=True, check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def _inv_sqrt(m: np.ndarray) -> np.ndarray:
    w, V = np.linalg.eigh(0.5 * (m + m.T))
    return (V / np.sqrt(np.maximum(w, 1e-30))) @ V.T


if __name__ == "__main__":
    sys.exit(main())
