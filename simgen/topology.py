"""Mesh topology for the solver (numpy, built once per model): hinges and the fixed Hessian pattern.

Hinges are the interior edges of a triangle mesh, each with its two wing vertices; they carry the
dihedral bending energy. The Hessian of the total energy is a 3x3-block sparse matrix with one
block per pair of vertices that share a triangle or a hinge (hinge wings couple through bending)
plus the diagonal. Its sparsity never changes during a simulation, so it is computed here once,
together with, for every element, the slot of each of its (i, j) blocks in the BSR values array:
kernels then accumulate into the values in place (atomics), with no rebuild per step.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from simgen.errors import InputError

__all__ = ["extract_hinges", "BsrPattern", "build_bsr_pattern", "stack_bsr_patterns"]


def extract_hinges(faces) -> tuple[np.ndarray, np.ndarray]:
    """Interior edges of a triangle mesh with their wing vertices.

    faces, int shape (F, 3). Returns ``hinges``, int64 shape (E, 4), rows (x0, x1, x2, x3), and
    ``hinge_faces``, int64 shape (E, 2), rows (face A, face B), one row per edge shared by exactly
    two faces, in order of first appearance. Orientation, which fixes the sign of the dihedral
    angle: face A traverses the edge from x0 to x1 (A's cyclic order is (x0, x1, x2)); x3 is the
    vertex of face B opposite the edge. The bending angle uses the normals
    (x1 - x0) x (x2 - x0) of A and (x3 - x0) x (x1 - x0) of B, which coincide on a flat,
    consistently oriented pair, so the angle is defined by the four points whatever B's own
    winding. Boundary edges give no hinge; an edge of three or more faces raises InputError.
    """
    faces = np.asarray(faces, dtype=np.int64)
    if faces.ndim != 2 or faces.shape[1] != 3:
        raise InputError(f"faces must have shape (F, 3), got {faces.shape}")
    nf = len(faces)
    if nf == 0:
        return np.zeros((0, 4), np.int64), np.zeros((0, 2), np.int64)
    # Directed half-edges (a -> b) with the opposite vertex, k-th edge of face f: (f[k], f[k+1]).
    a = faces.reshape(-1)
    b = faces[:, [1, 2, 0]].reshape(-1)
    opp = faces[:, [2, 0, 1]].reshape(-1)
    face_of = np.repeat(np.arange(nf), 3)
    lo, hi = np.minimum(a, b), np.maximum(a, b)
    nv = int(faces.max()) + 1
    key = lo * nv + hi
    order = np.argsort(key, kind="stable")  # stable: half-edges of an edge keep face order
    skey = key[order]
    starts = np.flatnonzero(np.r_[True, skey[1:] != skey[:-1]])
    counts = np.diff(np.r_[starts, len(skey)])
    if np.any(counts > 2):
        bad = order[starts[np.argmax(counts > 2)]]
        raise InputError(f"mesh is not manifold: edge ({int(a[bad])}, {int(b[bad])}) is shared by "
                         f"{int(counts.max())} triangles")
    interior = starts[counts == 2]
    h_a, h_b = order[interior], order[interior + 1]
    # Keep the order of first appearance in the face list (deterministic, cache friendly).
    first = np.argsort(h_a, kind="stable")
    h_a, h_b = h_a[first], h_b[first]
    hinges = np.stack([a[h_a], b[h_a], opp[h_a], opp[h_b]], axis=1)
    hinge_faces = np.stack([face_of[h_a], face_of[h_b]], axis=1)
    return hinges, hinge_faces


@dataclass
class BsrPattern:
    """Fixed 3x3-block sparsity of the Hessian and where each element writes into it (numpy).

    Block (i, j) couples vertices i and j; storage is BSR (CSR of 3x3 blocks), rows sorted, columns
    sorted within a row, both triangles of a symmetric pair stored.

    num_vertices: V (rows = columns of blocks).
    offsets, int32 shape (V + 1,): row r's blocks are slots offsets[r] .. offsets[r + 1] - 1.
    columns, int32 shape (nnz,): column of each slot.
    rows, int32 shape (nnz,): row of each slot (handy for kernels over slots, e.g. pinning).
    diag_slots, int32 shape (V,): slot of block (v, v).
    tri_slots, int32 shape (F, 9): slot of block (faces[t, a], faces[t, b]) at column a * 3 + b.
    hinge_slots, int32 shape (E, 16): slot of block (hinges[e, a], hinges[e, b]) at a * 4 + b.
    """

    num_vertices: int
    offsets: np.ndarray
    columns: np.ndarray
    rows: np.ndarray
    diag_slots: np.ndarray
    tri_slots: np.ndarray
    hinge_slots: np.ndarray

    @property
    def nnz(self) -> int:
        return int(len(self.columns))


def build_bsr_pattern(num_vertices: int, faces, hinges) -> BsrPattern:
    """The Hessian's block pattern: the diagonal, every vertex pair of a triangle, of a hinge.

    num_vertices: V; faces, int shape (F, 3); hinges, int shape (E, 4) (see :func:`extract_hinges`).
    """
    nv = int(num_vertices)
    faces = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    hinges = np.asarray(hinges, dtype=np.int64).reshape(-1, 4)
    if nv <= 0:
        raise InputError("the Hessian pattern needs at least one vertex")
    for name, idx in (("faces", faces), ("hinges", hinges)):
        if idx.size and (idx.min() < 0 or idx.max() >= nv):
            raise InputError(f"{name} index vertex {int(idx.max())} of {nv}")

    def pair_keys(elements: np.ndarray) -> np.ndarray:
        # (n, k) element vertex lists -> (n, k*k) keys row * V + col, local pair (a, b) at a*k + b.
        k = elements.shape[1]
        rows = np.repeat(elements, k, axis=1)
        cols = np.tile(elements, (1, k))
        return rows * nv + cols

    tri_keys = pair_keys(faces)
    hinge_keys = pair_keys(hinges)
    diag_keys = np.arange(nv, dtype=np.int64) * (nv + 1)
    keys = np.unique(np.concatenate([diag_keys, tri_keys.ravel(), hinge_keys.ravel()]))
    rows = keys // nv
    columns = keys % nv
    offsets = np.zeros(nv + 1, dtype=np.int64)
    np.cumsum(np.bincount(rows, minlength=nv), out=offsets[1:])
    return BsrPattern(
        num_vertices=nv,
        offsets=offsets.astype(np.int32),
        columns=columns.astype(np.int32),
        rows=rows.astype(np.int32),
        diag_slots=np.searchsorted(keys, diag_keys).astype(np.int32),
        tri_slots=np.searchsorted(keys, tri_keys).astype(np.int32).reshape(-1, 9),
        hinge_slots=np.searchsorted(keys, hinge_keys).astype(np.int32).reshape(-1, 16),
    )


def stack_bsr_patterns(patterns: list[BsrPattern]) -> BsrPattern:
    """The pattern of disjoint meshes taken in order (vertices, faces and hinges numbered on):
    block-diagonal, so each one's slots follow the previous ones' and nothing is sorted again. Equal
    to :func:`build_bsr_pattern` on the concatenated meshes, in O(nnz) instead of a sort."""
    if len(patterns) == 1:
        return patterns[0]
    vstart = np.r_[0, np.cumsum([p.num_vertices for p in patterns])]
    sstart = np.r_[0, np.cumsum([p.nnz for p in patterns])]
    if max(vstart[-1], sstart[-1]) >= 2**31:
        raise InputError(f"the stacked Hessian pattern has {sstart[-1]} blocks over {vstart[-1]} vertices, more "
                         "than its int32 indices hold")

    def cat(name: str, shift: np.ndarray) -> np.ndarray:
        return np.concatenate([getattr(p, name) + np.int32(o) for p, o in zip(patterns, shift)])

    offsets = np.r_[np.concatenate([p.offsets[:-1] + np.int32(o) for p, o in zip(patterns, sstart)]),
                    sstart[-1]].astype(np.int32)
    return BsrPattern(num_vertices=int(vstart[-1]), offsets=offsets, columns=cat("columns", vstart),
                      rows=cat("rows", vstart), diag_slots=cat("diag_slots", sstart),
                      tri_slots=cat("tri_slots", sstart).reshape(-1, 9),
                      hinge_slots=cat("hinge_slots", sstart).reshape(-1, 16))
