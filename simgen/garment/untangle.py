"""Untangling: cloth that already passes through itself is brought back to one side.

Self-contact (:mod:`simgen.sim.energies.self_contact`, :mod:`simgen.sim.impact_filter`) keeps an
untangled garment untangled; it cannot repair a state that is tangled already (an imported
garment, a coarse start, a slip of the solver), and would hold such a tangle in place. This module
repairs it, by global intersection analysis on the mesh graph (Baraff, Witkin and Kass, "Untangling
cloth", SIGGRAPH 2003) with the contour-shrinking moves of intersection contour minimisation
(Volino and Magnenat-Thalmann, SIGGRAPH 2006):

1. Find every crossing pair: an edge of the garment through a triangle of the garment that shares
   no vertex with it (:mod:`simgen.garment.crossings`, exact in float64).
2. Cut the garment's edge graph along the intersection contour: at the crossing edges and the
   edges of the triangles they cross. Where the contour is a closed loop on a layer (or ends where
   two layers are joined, as at a sleeve's fold), the cut separates what it encloses from the rest
   of the garment; the smaller side is the part that has gone through (BWK's rule).
3. For each crossing pair, move the crossing edge's vertex on the smaller side (the one nearer to
   the triangle's plane where the cut separates nothing: a local fold, a contour that ends on a
   boundary) through the triangle's plane to the other vertex's side, ``margin`` beyond it. With a
   reference (an earlier untangled state, as a simulation's frame start), a pair whose edge lay
   wholly on one side of the triangle then moves the vertex that has left that side: history
   decides where topology cannot. A pinned vertex stays and the triangle's free vertices move the
   other way instead. Moves requested of one vertex by several pairs are averaged.
4. Repeat until no edge crosses. Each round pushes the contour's inner rim back through, so the
   contour shrinks and closes, as in ICM.
5. With a reference, a crossing that ``ROLLBACK_AFTER`` rounds of moves have not removed is rolled
   back instead: the vertices of the pairs left and their neighbours move halfway to their
   reference positions each round. This takes the folds the moves cannot close: at a boundary,
   where pushing a fan vertex through the triangle's plane makes its other edges cross, and the
   next round pushes it back (a collar edge through its neighbour triangle in ``kick``, docs/sim.md,
   kept as a test case in tests/data/untangle_collar_fold.npz).

Until the roll-back, a vertex moves only while it is part of a crossing, by at most the depth it
has gone through plus the margin per round, and nothing else is touched; the roll-back also moves
the crossing's neighbours, toward the reference only. The result says how many rounds it took and whether
any crossing is left (a tangle that the rounds cannot shrink, e.g. two layers knotted through a
pinned region, is reported, not hidden).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from simgen.errors import InputError
from simgen.garment.crossings import CrossingCounter

__all__ = ["ROLLBACK_AFTER", "UntangleResult", "untangle"]

#: rounds of moves after which the crossings left are rolled back toward the reference (step 5)
ROLLBACK_AFTER = 10


@dataclass(frozen=True)
class UntangleResult:
    """positions [m] (V, 3) float64 untangled (or as far as the rounds got); crossings_before and
    crossings_after: crossing edges at the start and the end; rounds run; moved: vertices moved;
    max_displacement [m]: the largest distance a vertex ended from where it started."""

    positions: np.ndarray
    crossings_before: int
    crossings_after: int
    rounds: int
    moved: int
    max_displacement: float

    @property
    def untangled(self) -> bool:
        return self.crossings_after == 0


def _sides(edges: np.ndarray, cut: np.ndarray, num_vertices: int) -> tuple[np.ndarray, np.ndarray]:
    """Component label and component size of every vertex, (V,) each, in the edge graph without the
    ``cut`` edges (bool (E,))."""
    keep = edges[~cut]
    graph = coo_matrix((np.ones(len(keep)), (keep[:, 0], keep[:, 1])), shape=(num_vertices, num_vertices))
    _, labels = connected_components(graph, directed=False)
    return labels, np.bincount(labels)[labels]


def _cut(edges: np.ndarray, faces: np.ndarray, pairs: np.ndarray) -> np.ndarray:
    """The edges cut along the intersection contour, bool (E,): the crossing edges and the edges of
    the triangles they cross, so that the cut runs along both layers (a contour that ends where the
    layers are joined, as at a sleeve's fold, still separates what went through)."""
    cut = np.zeros(len(edges), dtype=bool)
    cut[pairs[:, 0]] = True
    tri = faces[np.unique(pairs[:, 1])]
    ring = np.sort(np.concatenate([tri[:, [0, 1]], tri[:, [1, 2]], tri[:, [2, 0]]]), axis=1)
    key = edges[:, 0].astype(np.int64) * (edges.max() + 1) + edges[:, 1]
    cut |= np.isin(key, ring[:, 0].astype(np.int64) * (edges.max() + 1) + ring[:, 1])
    return cut


def _plane_distances(x: np.ndarray, p, q, a, b, c) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Unit normals (P, 3) of triangles (a, b, c) and the signed distances [m] (P,) of p and q to
    their planes, at positions x [m] (V, 3)."""
    n = np.cross(x[b] - x[a], x[c] - x[a])
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)
    return n, np.einsum("ij,ij->i", x[p] - x[a], n), np.einsum("ij,ij->i", x[q] - x[a], n)


def _moves(x: np.ndarray, faces: np.ndarray, edges: np.ndarray, pairs: np.ndarray, free: np.ndarray,
           margin: float, reference: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """Summed displacement [m] (V, 3) and number of requests (V,) of one round (module doc, step 3)."""
    _, size = _sides(edges, _cut(edges, faces, pairs), len(x))
    p, q = edges[pairs[:, 0], 0], edges[pairs[:, 0], 1]
    a, b, c = (faces[pairs[:, 1], k] for k in range(3))
    n, dp, dq = _plane_distances(x, p, q, a, b, c)
    # The vertex that went through: on the smaller side of the cut, else the one nearer the plane;
    # with a reference, the one that is no longer on the side where both lay then.
    p_in = np.where(size[p] != size[q], size[p] < size[q], np.abs(dp) <= np.abs(dq))
    if reference is not None:
        _, rp, rq = _plane_distances(reference, p, q, a, b, c)
        known = np.sign(rp) * np.sign(rq) > 0
        p_in = np.where(known, np.sign(dp) != np.sign(rp), p_in)
    inside = np.where(p_in, p, q)
    d_in, d_out = np.where(p_in, dp, dq), np.where(p_in, dq, dp)
    depth = np.sign(d_out) * margin - d_in                     # signed travel along n to the far side
    total = np.zeros_like(x)
    hits = np.zeros(len(x))
    own = free[inside]
    np.add.at(total, inside[own], depth[own, None] * n[own])
    np.add.at(hits, inside[own], 1.0)
    # A pinned vertex stays: its triangle's free vertices move the other way instead.
    for k in (a, b, c):
        use = ~own & free[k]
        np.add.at(total, k[use], -depth[use, None] * n[use])
        np.add.at(hits, k[use], 1.0)
    return total, hits


def _roll_back(x: np.ndarray, reference: np.ndarray, edges: np.ndarray, faces: np.ndarray, pairs: np.ndarray,
               free: np.ndarray) -> None:
    """Move the free vertices of the crossing pairs and their neighbours halfway to the reference,
    in place (module doc, step 5)."""
    core = np.zeros(len(x), dtype=bool)
    core[edges[pairs[:, 0]].ravel()] = True
    core[faces[pairs[:, 1]].ravel()] = True
    ring = core.copy()
    touch = core[edges[:, 0]] | core[edges[:, 1]]
    ring[edges[touch].ravel()] = True
    ring &= free
    x[ring] = reference[ring] + 0.5 * (x[ring] - reference[ring])


def untangle(positions, faces, *, pinned=None, reference=None, margin: float = 5.0e-4, max_rounds: int = 200,
             device: str = "cpu", counter: CrossingCounter | None = None) -> UntangleResult:
    """Untangle a garment's positions (module doc).

    positions [m] (V, 3); faces (F, 3) int; pinned: bool (V,) vertices that must not move (default
    none); reference [m] (V, 3): an earlier untangled state of the same cloth (a simulation's frame
    start), whose sides decide which vertex went through wherever both ends of a crossing edge lay
    on one side of the triangle then, and toward which crossings left after ``ROLLBACK_AFTER``
    rounds are rolled back; margin [m]: how far beyond the other layer a moved vertex
    lands; max_rounds: the most detect-and-move rounds; device: where the crossings are found
    ("cpu", "cuda:0"); counter: a :class:`CrossingCounter` of these faces to reuse. Returns an
    :class:`UntangleResult`.
    """
    x = np.array(positions, dtype=np.float64)
    f = np.asarray(faces)
    if x.ndim != 2 or x.shape[1] != 3 or not np.all(np.isfinite(x)):
        raise InputError(f"positions must be finite with shape (V, 3), got {x.shape}")
    free = np.ones(len(x), dtype=bool) if pinned is None else ~np.asarray(pinned, dtype=bool)
    ref = None if reference is None else np.asarray(reference, dtype=np.float64)
    if ref is not None and ref.shape != x.shape:
        raise InputError(f"reference must have the positions' shape {x.shape}, got {ref.shape}")
    if free.shape != (len(x),):
        raise InputError(f"pinned must have shape ({len(x)},), got {free.shape}")
    if not margin > 0.0 or max_rounds < 1:
        raise InputError(f"margin must be > 0 and max_rounds >= 1, got {margin!r} and {max_rounds!r}")
    counter = counter or CrossingCounter(f, len(x), device)
    start = x.copy()
    pairs = counter.pairs(x)
    before = len(np.unique(pairs[:, 0]))
    rounds = 0
    while len(pairs) and rounds < max_rounds:
        if ref is not None and rounds >= ROLLBACK_AFTER:
            _roll_back(x, ref, counter.edges, f, pairs, free)
        else:
            total, hits = _moves(x, f, counter.edges, pairs, free, margin, ref)
            moving = hits > 0
            x[moving] += total[moving] / hits[moving, None]
        rounds += 1
        pairs = counter.pairs(x)
    shift = np.linalg.norm(x - start, axis=1)
    return UntangleResult(x, before, len(np.unique(pairs[:, 0])), rounds, int((shift > 0).sum()),
                          float(shift.max(initial=0.0)))
