"""Triangle-mesh topology and quality measures (numpy), for garment checks and OBJ import.

All functions take faces as an int array of shape (F, 3) (counter-clockwise seen from outside) and,
where geometry is needed, vertices [m] of shape (V, 3).
"""

from __future__ import annotations

import numpy as np

__all__ = [
    "unique_edges",
    "edge_face_counts",
    "non_manifold_edges",
    "boundary_loops",
    "is_consistently_oriented",
    "connected_components",
    "triangle_angles",
    "triangle_areas",
    "edge_lengths",
    "non_manifold_vertices",
]


def _directed_edges(faces: np.ndarray) -> np.ndarray:
    """The 3F directed half-edges (a -> b) in face order, shape (3F, 2)."""
    f = np.asarray(faces, dtype=np.int64)
    return np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]], axis=0)


def unique_edges(faces) -> np.ndarray:
    """Undirected edges, each once with the smaller index first, shape (E, 2), sorted."""
    e = np.sort(_directed_edges(faces), axis=1)
    return np.unique(e, axis=0)


def edge_face_counts(faces) -> tuple[np.ndarray, np.ndarray]:
    """Undirected edges (E, 2) and how many triangles share each, shape (E,)."""
    e = np.sort(_directed_edges(faces), axis=1)
    edges, counts = np.unique(e, axis=0, return_counts=True)
    return edges, counts


def non_manifold_edges(faces) -> np.ndarray:
    """Edges shared by more than two triangles, shape (K, 2)."""
    edges, counts = edge_face_counts(faces)
    return edges[counts > 2]


def is_consistently_oriented(faces) -> bool:
    """True when every interior edge is traversed once in each direction by its two triangles."""
    d = _directed_edges(faces)
    _, counts = np.unique(d, axis=0, return_counts=True)
    return bool(np.all(counts == 1))


def boundary_loops(faces) -> list[np.ndarray]:
    """Closed loops of boundary vertices, each ordered along the boundary half-edges.

    A boundary edge belongs to exactly one triangle. Raises ValueError when a vertex starts two
    boundary edges (two openings touching at one vertex), where loops are ambiguous.
    """
    d = _directed_edges(faces)
    key = np.sort(d, axis=1)
    _, inverse, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    boundary = d[counts[inverse.reshape(-1)] == 1]
    if len(boundary) == 0:
        return []
    starts, start_counts = np.unique(boundary[:, 0], return_counts=True)
    if np.any(start_counts > 1):
        raise ValueError(f"{int(np.sum(start_counts > 1))} vertices start two boundary edges (openings touch)")
    nxt = dict(zip(boundary[:, 0].tolist(), boundary[:, 1].tolist()))
    loops, seen = [], set()
    for v0 in boundary[:, 0].tolist():
        if v0 in seen:
            continue
        loop, v = [], v0
        while v not in seen:
            seen.add(v)
            loop.append(v)
            if v not in nxt:
                raise ValueError(f"boundary at vertex {v} does not close into a loop")
            v = nxt[v]
        loops.append(np.asarray(loop, dtype=np.int64))
    return loops


def non_manifold_vertices(faces) -> np.ndarray:
    """Vertices whose triangle fan is not a single disc or half-disc (bow-tie vertices), shape (K,).

    A vertex is manifold when the triangles around it form one connected fan through shared edges.
    Triangles with a repeated corner (degenerate) are ignored here; report them separately.
    """
    import scipy.sparse as sp
    from scipy.sparse.csgraph import connected_components as cc

    f = np.asarray(faces, dtype=np.int64)
    f = f[(f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2]) & (f[:, 2] != f[:, 0])]
    bad = []
    # Build corner list: for each vertex, the triangles incident to it; fans connect through edges.
    corners_v = f.reshape(-1)
    corners_f = np.repeat(np.arange(len(f)), 3)
    order = np.argsort(corners_v, kind="stable")
    corners_v, corners_f = corners_v[order], corners_f[order]
    splits = np.flatnonzero(np.diff(corners_v)) + 1
    for v, tris in zip(np.split(corners_v, splits), np.split(corners_f, splits)):
        if len(tris) < 2:
            continue
        vid = int(v[0])
        # The two other vertices of each incident triangle; triangles are adjacent if they share one.
        others = f[tris]
        others = others[others != vid].reshape(len(tris), 2)
        local = np.unique(others)
        idx = np.searchsorted(local, others)
        n = len(local)
        g = sp.coo_matrix((np.ones(len(tris)), (idx[:, 0], idx[:, 1])), shape=(n, n))
        ncomp, _ = cc(g, directed=False)
        if ncomp > 1:
            bad.append(vid)
    return np.asarray(bad, dtype=np.int64)


def connected_components(faces, num_vertices: int) -> tuple[int, np.ndarray]:
    """Components connected through triangles: (count, label per vertex, shape (V,)).

    Unreferenced vertices form components of their own.
    """
    import scipy.sparse as sp
    from scipy.sparse.csgraph import connected_components as cc

    e = unique_edges(faces)
    g = sp.coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(num_vertices, num_vertices))
    n, labels = cc(g, directed=False)
    return int(n), labels


def triangle_areas(vertices, faces) -> np.ndarray:
    """Triangle areas [m^2], shape (F,)."""
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    return 0.5 * np.linalg.norm(np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]), axis=1)


def triangle_angles(vertices, faces) -> np.ndarray:
    """Interior angles [deg] at the three corners of each triangle, shape (F, 3) (NaN if degenerate)."""
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    angles = np.empty(f.shape)
    for k in range(3):
        a = v[f[:, (k + 1) % 3]] - v[f[:, k]]
        b = v[f[:, (k + 2) % 3]] - v[f[:, k]]
        na = np.linalg.norm(a, axis=1)
        nb = np.linalg.norm(b, axis=1)
        with np.errstate(invalid="ignore", divide="ignore"):
            c = np.einsum("ij,ij->i", a, b) / (na * nb)
        angles[:, k] = np.degrees(np.arccos(np.clip(c, -1.0, 1.0)))
    return angles


def edge_lengths(vertices, edges) -> np.ndarray:
    """Lengths [m] of edges (E, 2), shape (E,)."""
    v = np.asarray(vertices, dtype=np.float64)
    e = np.asarray(edges, dtype=np.int64)
    return np.linalg.norm(v[e[:, 1]] - v[e[:, 0]], axis=1)
