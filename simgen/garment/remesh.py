"""Cutting a closed envelope along smooth curves and remeshing it to uniform triangles.

The openings of a garment (neck, hems, sleeve ends, armholes) are level sets ``k(p) = 0`` of a
smooth "keep" function (positive on the cloth). Cutting a fine mesh along them directly leaves
boundary edges of any length, and an isotropic remesher that keeps boundary vertices fixed (as
Botsch and Kobbelt's remesher in gpytoolbox does) cannot repair that. So the cut is made in three
steps:

1. :func:`split_along_level_set` inserts the curve ``k = 0`` into the closed fine mesh as a chain
   of edges (every triangle it crosses is split; no triangle is removed yet);
2. :func:`remesh` runs the remesher on the still closed mesh with that chain as *feature edges*:
   they are split and collapsed like any edge, but only along the chain, and their vertices stay
   on the original curve, so the curve comes out sampled at the target edge length;
3. :func:`cut` drops the triangles whose centroid has ``k < 0``; the curve becomes the boundary.

:func:`push_outside` then moves vertices that came closer than the clearance to the body.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

__all__ = ["split_along_level_set", "remesh", "cut", "push_outside", "mean_edge_length"]


def mean_edge_length(vertices: np.ndarray, faces: np.ndarray) -> float:
    """Mean length [m] of the unique edges of a mesh."""
    from simgen.garment.mesh import edge_lengths, unique_edges

    return float(edge_lengths(vertices, unique_edges(faces)).mean())


def split_along_level_set(vertices: np.ndarray, faces: np.ndarray, values: np.ndarray, *,
                          snap: float = 0.15) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Insert the zero level set of per-vertex ``values`` into a mesh as a chain of edges.

    vertices [m] (V, 3); faces (F, 3); values (V,): a smooth function sampled at the vertices,
    the curve is where its linear interpolation vanishes. A vertex closer to the curve than
    ``snap`` times the local edge length (measured along the crossing edges) has its value
    nudged off the curve first, so no sliver edge shorter than that is created.

    Returns (vertices (V', 3), faces (F', 3), curve_edges (K, 2)): the original vertices come
    first, the curve's vertices after them; faces keep their orientation.
    """
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    k = np.array(values, dtype=np.float64)
    k[k == 0.0] = 1e-12
    e = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    cross = (k[e[:, 0]] > 0) != (k[e[:, 1]] > 0)
    # Nudge vertices sitting almost on the curve: on a crossing edge (a, b) the crossing parameter
    # t = k_a / (k_a - k_b) must stay in [snap, 1 - snap], i.e. |k_a| >= snap / (1 - snap) |k_b|.
    ratio = snap / (1.0 - snap)
    for _ in range(4):
        ea, eb = e[cross, 0], e[cross, 1]
        required = np.zeros(len(k))
        np.maximum.at(required, ea, ratio * np.abs(k[eb]))
        np.maximum.at(required, eb, ratio * np.abs(k[ea]))
        low = np.abs(k) < required * (1.0 - 1e-9)
        if not low.any():
            break
        k[low] = np.sign(k[low]) * required[low]
        cross = (k[e[:, 0]] > 0) != (k[e[:, 1]] > 0)

    key = np.sort(e, axis=1)
    cross_keys, inverse = np.unique(key[cross], axis=0, return_inverse=True)
    a, b = cross_keys[:, 0], cross_keys[:, 1]
    t = (k[a] / (k[a] - k[b]))[:, None]
    new_points = v[a] + t * (v[b] - v[a])
    new_index = len(v) + np.arange(len(cross_keys))
    # Map every directed half-edge of f to its new vertex (or -1).
    edge_vertex = np.full(len(e), -1, dtype=np.int64)
    edge_vertex[np.flatnonzero(cross)] = new_index[inverse.reshape(-1)]
    nf = len(f)
    mid = edge_vertex.reshape(3, nf).T  # mid[:, 0]: on edge (0,1), [:, 1]: (1,2), [:, 2]: (2,0)

    split = (mid >= 0).sum(axis=1) == 2
    keep_faces = [f[~split]]
    curve = []
    fs, ms = f[split], mid[split]
    # Rotate each split triangle so that its lone vertex (the one whose two edges cross) is first.
    # Edge i joins corners i and i+1; the lone corner c is the one whose edges c-1 and c both cross.
    lone = np.where(ms[:, 2] >= 0, np.where(ms[:, 0] >= 0, 0, 2), 1)
    rows = np.arange(len(fs))
    c0 = fs[rows, lone]
    c1 = fs[rows, (lone + 1) % 3]
    c2 = fs[rows, (lone + 2) % 3]
    m01 = ms[rows, lone]  # on edge (c0, c1)
    m20 = ms[rows, (lone + 2) % 3]  # on edge (c2, c0)
    keep_faces.append(np.stack([c0, m01, m20], axis=1))
    allv = np.vstack([v, new_points])
    # The quad (m01, c1, c2, m20): split along its shorter diagonal.
    d1 = np.linalg.norm(allv[m01] - allv[c2], axis=1)
    d2 = np.linalg.norm(allv[c1] - allv[m20], axis=1)
    use1 = d1 <= d2
    q1 = np.concatenate([np.stack([m01, c1, c2], axis=1)[use1], np.stack([m01, c2, m20], axis=1)[use1]])
    q2 = np.concatenate([np.stack([m01, c1, m20], axis=1)[~use1], np.stack([c1, c2, m20], axis=1)[~use1]])
    keep_faces += [q1, q2]
    curve = np.sort(np.stack([m01, m20], axis=1), axis=1)
    return allv, np.concatenate(keep_faces), np.unique(curve, axis=0)


def remesh(vertices: np.ndarray, faces: np.ndarray, edge_length: float, *, curve_edges: np.ndarray | None = None,
           iterations: int = 10, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Isotropic remeshing (Botsch and Kobbelt 2004, gpytoolbox's implementation).

    vertices [m] (V, 3), faces (F, 3); edge_length [m]: target; curve_edges (K, 2): feature edges
    kept as a chain (split and collapsed only along it, vertices stay on it). Vertices are
    projected back onto the input surface after every iteration. ``seed`` != 0 shuffles the
    order in which the remesher meets vertices and triangles: the result is an equally good but
    different triangulation of the same surface. Returns (vertices (V', 3), faces (F', 3)).
    """
    import gpytoolbox

    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    fe = np.zeros((0, 2), dtype=np.int64) if curve_edges is None else np.asarray(curve_edges, dtype=np.int64)
    if seed:
        rng = np.random.default_rng(seed)
        perm = rng.permutation(len(v))
        inv = np.empty_like(perm)
        inv[perm] = np.arange(len(v))
        v, f, fe = v[perm], inv[f][rng.permutation(len(f))], inv[fe]
    u, g = gpytoolbox.remesh_botsch(v, f.astype(np.int32), i=int(iterations), h=float(edge_length), project=True,
                                    feature_edges=fe.astype(np.int32))
    return np.asarray(u, dtype=np.float64), np.asarray(g, dtype=np.int64)


def cut(vertices: np.ndarray, faces: np.ndarray,
        keep: Callable[[np.ndarray], np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """Remove the triangles whose centroid has ``keep(centroid) < 0``; keep the largest remaining piece.

    keep: maps points [m] (N, 3) to values (N,), positive on the cloth. Unreferenced vertices are
    dropped. Returns (vertices, faces).
    """
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    return _largest_piece(v, f[keep(v[f].mean(axis=1)) > 0.0])


def _largest_piece(v: np.ndarray, f: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Keep the connected piece with the most triangles; drop unreferenced vertices."""
    from simgen.garment.mesh import connected_components

    n, labels = connected_components(f, len(v))
    if n > 1:
        largest = np.bincount(labels[f[:, 0]]).argmax()
        f = f[labels[f[:, 0]] == largest]
    used = np.unique(f)
    remap = np.full(len(v), -1, dtype=np.int64)
    remap[used] = np.arange(len(used))
    return v[used], remap[f]


def repair_bowties(vertices: np.ndarray, faces: np.ndarray, *,
                   max_rounds: int = 10) -> tuple[np.ndarray, np.ndarray, int]:
    """Remove the smaller triangle fans at vertices where the cloth touches itself in one point.

    A cut along a curve that is not exactly a chain of mesh edges can leave a vertex whose kept
    triangles form two fans joined only at that vertex (a bow-tie: two pieces of boundary meet
    there). Every fan but the largest is deleted, then the largest connected piece is kept.
    Returns (vertices, faces, triangles removed).
    """
    from simgen.garment.mesh import non_manifold_vertices

    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    removed = 0
    for _ in range(max_rounds):
        bad = non_manifold_vertices(f)
        if len(bad) == 0:
            break
        drop = np.zeros(len(f), dtype=bool)
        for vid in bad.tolist():
            tris = np.flatnonzero((f == vid).any(axis=1))
            # Flood the fan through triangles sharing an edge incident to vid.
            label = -np.ones(len(tris), dtype=np.int64)
            others = [set(f[t].tolist()) - {vid} for t in tris]
            n_fans = 0
            for start in range(len(tris)):
                if label[start] >= 0:
                    continue
                stack, label[start] = [start], n_fans
                while stack:
                    i = stack.pop()
                    for j in range(len(tris)):
                        if label[j] < 0 and others[i] & others[j]:
                            label[j] = n_fans
                            stack.append(j)
                n_fans += 1
            keep_fan = np.bincount(label).argmax()
            drop[tris[label != keep_fan]] = True
        removed += int(drop.sum())
        f = f[~drop]
    v, f = _largest_piece(v, f)
    return v, f, removed


def _boundary_edge_mask(f: np.ndarray) -> np.ndarray:
    """(F, 3) bool: whether edge k of face i (corners k, k+1) is a boundary edge."""
    nf = len(f)
    he = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    _, inverse, counts = np.unique(np.sort(he, axis=1), axis=0, return_inverse=True, return_counts=True)
    return (counts[inverse.reshape(-1)] == 1).reshape(3, nf).T


def _boundary_vertex_mask(f: np.ndarray, n: int) -> np.ndarray:
    mask = _boundary_edge_mask(f)
    out = np.zeros(n, dtype=bool)
    rows, cols = np.nonzero(mask)
    out[f[rows, cols]] = True
    out[f[rows, (cols + 1) % 3]] = True
    return out


def collapse_short_edges(vertices: np.ndarray, faces: np.ndarray, threshold: float, *,
                         boundary_only: bool = False) -> tuple[np.ndarray, np.ndarray, int]:
    """Collapse edges shorter than ``threshold`` [m], shortest first.

    A boundary edge collapses to its midpoint; an edge from an interior vertex to a boundary
    vertex collapses onto the boundary vertex (openings do not move); an interior edge collapses
    to its midpoint. Edges joining two boundary vertices through the interior are left alone
    (collapsing them would pinch the cloth). A collapse is made only when it keeps the mesh
    manifold (the ends share exactly the neighbours opposite the edge) and turns no triangle
    over (normals turn by less than about 70 degrees). ``boundary_only`` restricts it to boundary
    edges. Returns (vertices, faces, collapses made).
    """
    v = np.array(vertices, dtype=np.float64)
    f = np.array(faces, dtype=np.int64)
    total = 0
    for _ in range(10):
        on_boundary = _boundary_vertex_mask(f, len(v))
        bmask = _boundary_edge_mask(f)
        edges = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
        is_bedge = np.concatenate([bmask[:, 0], bmask[:, 1], bmask[:, 2]])
        key = np.sort(edges, axis=1)
        key, first = np.unique(key, axis=0, return_index=True)
        is_bedge = is_bedge[first]
        length = np.linalg.norm(v[key[:, 0]] - v[key[:, 1]], axis=1)
        both = on_boundary[key[:, 0]] & on_boundary[key[:, 1]]
        allowed = (length < threshold) & (~both | is_bedge)
        if boundary_only:
            allowed &= is_bedge
        cand = np.flatnonzero(allowed)
        if len(cand) == 0:
            break
        normals = _face_normals(v, f)
        vf: list[list[int]] = [[] for _ in range(len(v))]
        for i, tri in enumerate(f.tolist()):
            for x in tri:
                vf[x].append(i)
        alive = np.ones(len(f), dtype=bool)
        touched = np.zeros(len(v), dtype=bool)
        done = 0
        for e in cand[np.argsort(length[cand])].tolist():
            a, b = int(key[e, 0]), int(key[e, 1])
            if touched[a] or touched[b]:
                continue
            if on_boundary[a] and not on_boundary[b]:
                keep_v, gone, pos = a, b, v[a].copy()
            elif on_boundary[b] and not on_boundary[a]:
                keep_v, gone, pos = b, a, v[b].copy()
            else:
                keep_v, gone, pos = a, b, 0.5 * (v[a] + v[b])
            fa = [t for t in vf[keep_v] if alive[t]]
            fb = [t for t in vf[gone] if alive[t]]
            shared = [t for t in fb if keep_v in f[t]]
            na = {x for t in fa for x in f[t].tolist()} - {keep_v}
            nb = {x for t in fb for x in f[t].tolist()} - {gone}
            opposite = {x for t in shared for x in f[t].tolist()} - {keep_v, gone}
            if (na & nb) != opposite or len(shared) != (1 if is_bedge[e] else 2):
                continue
            moved = [t for t in set(fa) | set(fb) if t not in shared]
            trial = f[moved].copy()
            trial[trial == gone] = keep_v
            vv = v.copy()
            vv[keep_v] = pos
            if len(moved) and np.any(np.einsum("ij,ij->i", _face_normals(vv, trial), normals[moved]) < 0.35):
                continue
            v[keep_v] = pos
            f[moved] = trial
            alive[shared] = False
            for t in moved:
                if t not in vf[keep_v]:
                    vf[keep_v].append(t)
            touched[[keep_v, gone]] = True
            touched[list(opposite)] = True
            done += 1
        f = f[alive]
        total += done
        if done == 0:
            break
    v, f = _largest_piece(v, f)
    return v, f, total


def split_long_boundary_edges(vertices: np.ndarray, faces: np.ndarray,
                              threshold: float) -> tuple[np.ndarray, np.ndarray, int]:
    """Split boundary edges longer than ``threshold`` [m] at their midpoints (and their triangle in two).

    Needs at most one boundary edge per triangle (no ears; see :func:`clean_boundary`).
    Returns (vertices, faces, splits made).
    """
    v = np.asarray(vertices, dtype=np.float64)
    f = np.array(faces, dtype=np.int64)
    total = 0
    for _ in range(4):
        mask = _boundary_edge_mask(f)
        mask &= (mask.sum(axis=1) == 1)[:, None]
        rows, cols = np.nonzero(mask)
        a, b, c = f[rows, cols], f[rows, (cols + 1) % 3], f[rows, (cols + 2) % 3]
        long = np.linalg.norm(v[a] - v[b], axis=1) > threshold
        if not long.any():
            break
        rows, a, b, c = rows[long], a[long], b[long], c[long]
        m = len(v) + np.arange(len(rows))
        v = np.vstack([v, 0.5 * (v[a] + v[b])])
        f[rows] = np.stack([a, m, c], axis=1)
        f = np.vstack([f, np.stack([m, b, c], axis=1)])
        total += len(rows)
    return v, f, total


def clean_boundary(vertices: np.ndarray, faces: np.ndarray, edge_length: float, *, short: float = 0.6,
                   long: float = 1.4, max_rounds: int = 10) -> tuple[np.ndarray, np.ndarray]:
    """Regularise the openings after a cut: no ears, boundary edges within [short, long] x edge_length.

    An ear is a triangle with two boundary edges (a spike where the opening turns sharply); it is
    removed. Boundary edges longer than ``long * edge_length`` are split, shorter than
    ``short * edge_length`` collapsed (:func:`collapse_short_edges`). The new or moved boundary
    vertices are put back on the opening's curve by :func:`snap_boundary`. Returns (vertices, faces).
    """
    v = np.array(vertices, dtype=np.float64)
    f = np.array(faces, dtype=np.int64)
    for _ in range(max_rounds):
        ears = _boundary_edge_mask(f).sum(axis=1) >= 2
        if not ears.any():
            break
        v, f = _largest_piece(v, f[~ears])
        v, f, _ = repair_bowties(v, f)
    v, f, _ = split_long_boundary_edges(v, f, long * edge_length)
    v, f, _ = collapse_short_edges(v, f, short * edge_length, boundary_only=True)
    return v, f


def snap_boundary(vertices: np.ndarray, faces: np.ndarray, keep: Callable[[np.ndarray], np.ndarray],
                  reference: tuple[np.ndarray, np.ndarray], *, iterations: int = 12, spacing_iterations: int = 8,
                  tolerance: float = 1e-4) -> tuple[np.ndarray, int]:
    """Put the boundary vertices on the curve ``keep = 0``, evenly spaced, on the reference surface.

    The remesher keeps its feature chains on the curve almost everywhere, but where an opening
    turns sharply at a coarse edge length a chain vertex can end up beside it, and the cut then
    follows a mesh edge off the curve. Each iteration moves every boundary vertex half-way to the
    midpoint of its two boundary neighbours (the first ``spacing_iterations`` only: this evens
    out the spacing along the loop), then takes a Newton step along the surface gradient of
    ``keep`` (central differences, 0.1 mm) and projects onto the reference surface.
    Returns (vertices, number of boundary vertices that were off the curve by more than
    ``tolerance`` [m] before).
    """
    from simgen.body.surface import project_to_surface
    from simgen.garment.mesh import boundary_loops

    v = np.array(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    loops = boundary_loops(f)
    if not loops:
        return v, 0
    b = np.concatenate(loops)
    prev = np.concatenate([np.roll(loop, 1) for loop in loops])
    nxt = np.concatenate([np.roll(loop, -1) for loop in loops])
    off = int(np.sum(np.abs(keep(v[b])) > tolerance))
    eps = 1e-4
    offsets = np.vstack([np.eye(3), -np.eye(3)]) * eps
    rv, rf = reference
    for it in range(iterations):
        p = v[b]
        if it < spacing_iterations:
            p = p + 0.5 * (0.5 * (v[prev] + v[nxt]) - p)
        k = keep(p)
        samples = keep((p[:, None, :] + offsets[None]).reshape(-1, 3)).reshape(len(p), 6)
        grad = (samples[:, :3] - samples[:, 3:]) / (2.0 * eps)
        proj = project_to_surface(p, rv, rf)
        tri = rf[proj.face]
        n = np.cross(rv[tri[:, 1]] - rv[tri[:, 0]], rv[tri[:, 2]] - rv[tri[:, 0]])
        n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)
        g = grad - np.einsum("ij,ij->i", grad, n)[:, None] * n
        step = -(k / np.maximum(np.einsum("ij,ij->i", g, g), 1e-12))[:, None] * g
        v[b] = project_to_surface(p + step, rv, rf).closest
        if it >= spacing_iterations and np.all(np.abs(keep(v[b])) <= tolerance):
            break
    return v, off


def _face_normals(v: np.ndarray, f: np.ndarray) -> np.ndarray:
    n = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)


def delaunay_flips(vertices: np.ndarray, faces: np.ndarray, *, max_rounds: int = 20) -> tuple[np.ndarray, int]:
    """Flip interior edges whose two opposite angles sum to more than 180 degrees.

    A flip is made only when the new edge does not exist yet and both new triangles keep the
    orientation of the old ones (their normals turn by less than 60 degrees), so the surface and
    its boundary are unchanged. Returns (faces, number of flips).
    """
    v = np.asarray(vertices, dtype=np.float64)
    f = np.array(faces, dtype=np.int64)
    flips = 0
    for _ in range(max_rounds):
        nf = len(f)
        he = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])  # half-edge i of face i % nf
        opp = np.concatenate([f[:, 2], f[:, 0], f[:, 1]])
        face_of = np.tile(np.arange(nf), 3)
        key = he[:, 0] * len(v) + he[:, 1]
        rev = he[:, 1] * len(v) + he[:, 0]
        order = np.argsort(key)
        pos = np.searchsorted(key[order], rev)
        pos = np.minimum(pos, len(key) - 1)
        twin = np.where(key[order][pos] == rev, order[pos], -1)
        cand = np.flatnonzero((twin >= 0) & (he[:, 0] < he[:, 1]))
        a, b = he[cand, 0], he[cand, 1]
        c, d = opp[cand], opp[twin[cand]]

        def angle_at(p, q, r):  # angle at p in triangle p, q, r
            u, w = v[q] - v[p], v[r] - v[p]
            norms = np.linalg.norm(u, axis=1) * np.linalg.norm(w, axis=1)
            cos = np.einsum("ij,ij->i", u, w) / np.maximum(norms, 1e-300)
            return np.arccos(np.clip(cos, -1.0, 1.0))

        bad = angle_at(c, a, b) + angle_at(d, a, b) > np.pi + 1e-6
        if not bad.any():
            break
        cand, a, b, c, d = cand[bad], a[bad], b[bad], c[bad], d[bad]
        # Process the worst first; skip flips touching a face already changed in this round.
        existing = set((np.minimum(he[:, 0], he[:, 1]) * len(v) + np.maximum(he[:, 0], he[:, 1])).tolist())
        normals = _face_normals(v, f)
        used = np.zeros(nf, dtype=bool)
        changed = 0
        for e_idx, ai, bi, ci, di in zip(cand.tolist(), a.tolist(), b.tolist(), c.tolist(), d.tolist()):
            f1, f2 = face_of[e_idx], face_of[twin[e_idx]]
            if used[f1] or used[f2] or ci == di:
                continue
            if min(ci, di) * len(v) + max(ci, di) in existing:
                continue
            # Half-edge a->b lies in f1 = (a, b, c); its twin b->a in f2 = (b, a, d).
            t1, t2 = np.array([[ci, di, bi]]), np.array([[di, ci, ai]])
            n1, n2 = _face_normals(v, t1)[0], _face_normals(v, t2)[0]
            ref = normals[f1] + normals[f2]
            ref /= max(np.linalg.norm(ref), 1e-300)
            if n1 @ ref < 0.5 or n2 @ ref < 0.5:
                continue
            f[f1], f[f2] = t1[0], t2[0]
            used[f1] = used[f2] = True
            existing.add(min(ci, di) * len(v) + max(ci, di))
            changed += 1
        flips += changed
        if changed == 0:
            break
    return f, flips


def relax(vertices: np.ndarray, faces: np.ndarray, reference: tuple[np.ndarray, np.ndarray], *,
          edge_length: float | None = None, iterations: int = 5, step: float = 0.5) -> tuple[np.ndarray, np.ndarray]:
    """Improve triangle shapes without moving the boundary: collapses, flips and tangential smoothing.

    Edges shorter than half ``edge_length`` [m] (when given) are collapsed first
    (:func:`collapse_short_edges`: an interior vertex crowding an opening merges into it). Each
    iteration then flips edges (:func:`delaunay_flips`), moves every interior vertex ``step`` of
    the way to the mean of its neighbours within its tangent plane, and projects it back onto the
    ``reference`` surface (vertices (R, 3), faces) it was cut from. Returns (vertices, faces).
    """
    import scipy.sparse as sp

    from simgen.body.surface import project_to_surface
    from simgen.garment.mesh import boundary_loops, unique_edges

    v = np.array(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    if edge_length is not None:
        v, f, _ = collapse_short_edges(v, f, 0.5 * edge_length)
    interior = np.ones(len(v), dtype=bool)
    for loop in boundary_loops(f):
        interior[loop] = False
    for _ in range(iterations):
        f, _ = delaunay_flips(v, f)
        e = unique_edges(f)
        adj = sp.coo_matrix((np.ones(2 * len(e)), (np.r_[e[:, 0], e[:, 1]], np.r_[e[:, 1], e[:, 0]])),
                            shape=(len(v), len(v))).tocsr()
        mean = (adj @ v) / np.maximum(np.asarray(adj.sum(axis=1)), 1.0)
        fn = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])  # area-weighted
        vn = np.zeros_like(v)
        for k in range(3):
            np.add.at(vn, f[:, k], fn)
        vn /= np.maximum(np.linalg.norm(vn, axis=1, keepdims=True), 1e-300)
        delta = step * (mean - v)
        delta -= np.einsum("ij,ij->i", delta, vn)[:, None] * vn
        moved = v[interior] + delta[interior]
        v[interior] = project_to_surface(moved, reference[0], reference[1]).closest
    f, _ = delaunay_flips(v, f)
    return v, f


def push_outside(vertices: np.ndarray, body_vertices: np.ndarray, body_faces: np.ndarray, clearance: float, *,
                 max_rounds: int = 5) -> tuple[np.ndarray, int]:
    """Move every vertex closer to the body than ``clearance`` [m] (or inside it) out to that distance.

    Each offending vertex moves along the direction from its closest body point (reversed when it
    is inside), which is the body's outward normal there. Returns (vertices, number moved).
    """
    from simgen.body.surface import project_to_surface

    v = np.array(vertices, dtype=np.float64)
    moved = np.zeros(len(v), dtype=bool)
    for _ in range(max_rounds):
        proj = project_to_surface(v, body_vertices, body_faces)
        bad = proj.signed_distance < clearance
        if not bad.any():
            break
        direction = v[bad] - proj.closest[bad]
        norm = np.linalg.norm(direction, axis=1, keepdims=True)
        direction = np.sign(proj.signed_distance[bad])[:, None] * direction / np.maximum(norm, 1e-12)
        # A vertex exactly on the surface has no direction: use the closest triangle's normal.
        flat = norm[:, 0] < 1e-9
        if flat.any():
            tri = body_faces[proj.face[bad][flat]]
            bv = body_vertices
            n = np.cross(bv[tri[:, 1]] - bv[tri[:, 0]], bv[tri[:, 2]] - bv[tri[:, 0]])
            direction[flat] = n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
        v[bad] = proj.closest[bad] + clearance * 1.05 * direction
        moved |= bad
    return v, int(moved.sum())
