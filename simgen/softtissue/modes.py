"""Modal analysis of the flesh: the free vibration frequencies K phi = omega^2 M phi of one instance,
and which body region a mode lives in.

K is the solver's own operator, read back column by column: nodes are coloured so that no two of
one colour share a neighbour, and one product of K with the sum of a colour's unit vectors (per
axis) gives all their columns at once (:func:`stiffness_matrix`). The lowest modes come from a
shift-invert Lanczos (scipy) on the free degrees of freedom.
"""

from __future__ import annotations

import numpy as np
import warp as wp

from simgen.softtissue.model import FleshModel
from simgen.softtissue.solver import FleshSolver

__all__ = ["stiffness_matrix", "modal_frequencies", "region_modes"]


def _distance2_colouring(tets: np.ndarray, n: int) -> np.ndarray:
    import scipy.sparse as sp

    pairs = np.concatenate([tets[:, [a, b]] for a in range(4) for b in range(4)])
    adj = sp.coo_matrix((np.ones(len(pairs), dtype=np.int32), (pairs[:, 0], pairs[:, 1])), shape=(n, n)).tocsr()
    adj.data[:] = 1
    two = (adj @ adj).tocsr()
    colour = np.full(n, -1)
    for i in range(n):
        used = colour[two.indices[two.indptr[i]:two.indptr[i + 1]]]
        free = np.setdiff1d(np.arange(len(used) + 1), used[used >= 0])
        colour[i] = free[0]
    return colour


def stiffness_matrix(solver: FleshSolver, instance: int = 0):
    """K of one instance as a scipy CSR matrix (3 Nn x 3 Nn) [N/m], from the solver's operator."""
    import scipy.sparse as sp

    m = solver.model
    nn, tets = m.num_nodes, m.tets_host
    colour = _distance2_colouring(tets, nn)
    pairs = np.concatenate([tets[:, [a, b]] for a in range(4) for b in range(4)])
    pairs = np.unique(pairs, axis=0)                                          # (row node, column node)
    rows, cols, vals = [], [], []
    probe = np.zeros((m.total_nodes, 3), dtype=np.float32)
    x = wp.zeros(m.total_nodes, dtype=wp.vec3, device=m.device)
    out = wp.zeros(m.total_nodes, dtype=wp.vec3, device=m.device)
    base = instance * nn
    for c in range(colour.max() + 1):
        members = np.nonzero(colour == c)[0]
        sel = np.isin(pairs[:, 1], members)
        r, col = pairs[sel, 0], pairs[sel, 1]
        for d in range(3):
            probe[:] = 0.0
            probe[base + members, d] = 1.0
            x.assign(probe)
            k = solver.stiffness(x, out).numpy()[base:base + nn].astype(np.float64)
            for e in range(3):
                rows.append(3 * r + e)
                cols.append(3 * col + d)
                vals.append(k[r, e])
    K = sp.coo_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(3 * nn, 3 * nn))
    return K.tocsr()


def modal_frequencies(solver: FleshSolver, count: int = 40, instance: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """The ``count`` lowest natural frequencies [Hz] of one instance (free nodes) and the mode shapes
    (3 Nn, count), M-normalised, zero on pinned nodes."""
    import scipy.sparse as sp
    import scipy.sparse.linalg as spla

    m = solver.model
    K = stiffness_matrix(solver, instance)
    mass = np.repeat(m.mass[instance], 3)
    free = np.repeat(~m.pinned[instance], 3)
    idx = np.nonzero(free)[0]
    Kf = K[idx][:, idx]
    Mf = sp.diags(mass[idx])
    w2, phi = spla.eigsh(Kf.tocsc(), k=min(count, len(idx) - 2), M=Mf.tocsc(), sigma=0.0, which="LM")
    order = np.argsort(w2)
    modes = np.zeros((3 * m.num_nodes, len(order)))
    modes[idx] = phi[:, order]
    return np.sqrt(np.maximum(w2[order], 0.0)) / (2 * np.pi), modes


def region_modes(solver: FleshSolver, regions: dict, count: int = 40, share: float = 0.5, instance: int = 0) -> dict:
    """For each region (name -> node mask (Nn,)), the lowest frequency [Hz] among the ``count`` lowest
    modes whose kinetic energy lies at least ``share`` in that region (None if none does)."""
    freqs, modes = modal_frequencies(solver, count, instance)
    mass = np.repeat(solver.model.mass[instance], 3)
    energy = mass[:, None] * modes ** 2
    total = energy.sum(axis=0)
    out = {}
    for name, mask in regions.items():
        part = energy[np.repeat(mask, 3)].sum(axis=0) / total
        hit = np.nonzero(part >= share)[0]
        out[name] = float(freqs[hit[0]]) if len(hit) else None
    return out
