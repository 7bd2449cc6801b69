"""Garment skinning: weights borrowed from the body, linear blend skinning and its inverse (numpy, float64).

Skinning weights of a garment come from the template body in rest pose (``body.v_template``,
``body.faces``, ``body.weights``), never from a shaped or posed body:

- ``method="closest"`` (thesis ch. 4): each garment vertex is projected onto the closest triangle of
  the template body and gets that triangle's three vertex weights blended with the barycentric
  coordinates of the closest point. On the body surface this reproduces the body's weights exactly.
- ``method="diffused"`` (thesis ch. 6, eq. 6.4): W~(p) = 1/N sum_n W(phi(q_n)), q_n ~ N(p, s(p)^2 I),
  phi the closest body surface point. Points between the legs, under a skirt, then draw on both legs
  instead of following whichever leg happens to be closer. The weights are then smoothed on the
  garment mesh with a few explicit uniform-Laplacian steps (our addition to eq. 6.4).

The skinning transforms that drive a garment are those of the body it is dressed on: for a shaped
body (betas != 0) they are ``body.forward(betas, pose, trans).transforms``, which map points of the
*shaped* rest body to the posed world. A garment's rest vertices (on the template body) must first
be carried to the shaped rest body, e.g. with :func:`shape_offsets` (the body's shape blendshape
diffused to the garment, eq. 6.5), before :func:`lbs` poses them.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from simgen.errors import InputError

__all__ = [
    "SKINNING_METHODS",
    "DEFAULT_NUM_SAMPLES",
    "DEFAULT_SIGMA",
    "DEFAULT_SMOOTHING_ITERATIONS",
    "SMOOTHING_STEP",
    "compute_skin_weights",
    "shape_offsets",
    "closest_body_points",
    "BodyPoints",
    "lbs",
    "inverse_lbs",
    "laplacian_smooth",
]

SKINNING_METHODS = ("closest", "diffused")
#: Samples per point of eq. 6.4 (rounded up to a multiple of 8, see :func:`compute_skin_weights`).
DEFAULT_NUM_SAMPLES = 64
#: Smallest standard deviation [m] of the Gaussian samples of eq. 6.4; it grows with the distance to the body.
DEFAULT_SIGMA = 0.02
#: Explicit uniform-Laplacian steps applied to diffused weights on the garment mesh.
DEFAULT_SMOOTHING_ITERATIONS = 5
#: Step of each Laplacian iteration: w <- (1 - step) w + step * mean of the neighbours' w.
SMOOTHING_STEP = 0.5

# Surface queries per call of the Warp projection: bounds the memory of the diffused variant
# (a 200k-triangle import with 64 samples per vertex is ~6M queries).
_QUERY_CHUNK = 1 << 18
# Frames per block in lbs/inverse_lbs: the blended transforms take 96 bytes per vertex and frame.
_FRAME_CHUNK = 16


# --------------------------------------------------------------------------- body surface queries
@dataclass
class BodyPoints:
    """Closest points of query points on the template body surface (float64).

    face, int shape (P,): closest body triangle; bary, shape (P, 3): barycentric coordinates of the
    closest point in that triangle (non-negative, summing to 1); distance [m], shape (P,): signed
    distance to the body (negative inside).
    """

    face: np.ndarray
    bary: np.ndarray
    distance: np.ndarray

    def blend(self, body_faces: np.ndarray, field: np.ndarray) -> np.ndarray:
        """Barycentric blend of a per-body-vertex field (Vb, K) at the closest points -> (P, K)."""
        corners = field[body_faces[self.face]]  # (P, 3, K)
        return np.einsum("pc,pck->pk", self.bary, corners)


def closest_body_points(points, body, *, device: str | None = "cpu") -> BodyPoints:
    """Closest points of ``points`` [m], shape (P, 3), on the template body (rest pose, betas = 0),
    queried on the Warp ``device`` (the CPU by default).

    The body-surface query (:func:`simgen.body.surface.project_to_surface`, winding-number sign):
    the closest triangle from Warp's BVH, the barycentric coordinates exact in float64 on it (a
    point at a body vertex gets exactly (1, 0, 0), one over a face its exact in-plane coordinates,
    so "closest" weights reproduce the body weights on the body surface to machine precision).
    Returns :class:`BodyPoints`.
    """
    from simgen.body.surface import SurfaceMesh

    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    surface = SurfaceMesh(body.v_template, body.faces, device=device)
    face = np.empty(len(pts), dtype=np.int64)
    bary = np.empty((len(pts), 3))
    dist = np.empty(len(pts))
    for start in range(0, len(pts), _QUERY_CHUNK):
        sl = slice(start, start + _QUERY_CHUNK)
        proj = surface.project(pts[sl])
        if np.any(proj.face < 0) or not np.all(np.isfinite(proj.bary)):
            raise InputError(f"body model {body.name!r}: no (non-degenerate) closest triangle found for "
                             f"some points")
        b = np.clip(proj.bary, 0.0, None)
        face[sl], bary[sl], dist[sl] = proj.face, b / b.sum(axis=1, keepdims=True), proj.signed_distance
    return BodyPoints(face=face, bary=bary, distance=dist)


def _sample_offsets(num_samples: int, seed: int) -> np.ndarray:
    """Standard-normal offsets (N, 3), N = num_samples rounded up to a multiple of 8.

    Each base draw is used with all 8 sign patterns of its coordinates: the set is symmetric under
    the reflection of each axis (its mean is exactly zero and a point on a body's mirror plane sees
    a mirror-symmetric sample pattern).
    """
    base = np.random.default_rng(seed).standard_normal((-(-num_samples // 8), 3))
    signs = np.array([[sx, sy, sz] for sx in (1, -1) for sy in (1, -1) for sz in (1, -1)], dtype=np.float64)
    return (base[:, None, :] * signs[None]).reshape(-1, 3)


def _diffused_field(points: np.ndarray, body, field: np.ndarray, std: np.ndarray, offsets: np.ndarray,
                    device: str | None = "cpu") -> np.ndarray:
    """Eq. 6.4 for any per-body-vertex field (Vb, K): the mean of the closest-point field over
    q_n = p + std(p) * offsets_n. points (P, 3), std [m] (P,), offsets (N, 3) -> (P, K)."""
    n = len(offsets)
    out = np.empty((len(points), field.shape[1]))
    per_chunk = max(1, _QUERY_CHUNK // n)
    for start in range(0, len(points), per_chunk):
        sl = slice(start, start + per_chunk)
        q = points[sl, None, :] + std[sl, None, None] * offsets[None]  # (c, N, 3)
        near = closest_body_points(q.reshape(-1, 3), body, device=device)
        out[sl] = near.blend(body.faces, field).reshape(-1, n, field.shape[1]).mean(axis=1)
    return out


def _diffused(points: np.ndarray, body, field: np.ndarray, num_samples, sigma, seed,
             device: str | None = "cpu") -> np.ndarray:
    """Eq. 6.4 / 6.5 at garment points with the sampling of :func:`compute_skin_weights`:
    s(p) = max(sigma, |d(p)|), num_samples shared offsets drawn from seed; the body queried on the
    Warp ``device``. -> (P, K)."""
    if isinstance(num_samples, bool) or not isinstance(num_samples, (int, np.integer)) or num_samples < 1:
        raise InputError(f"num_samples must be a positive integer, got {num_samples!r}")
    if not (isinstance(sigma, (int, float, np.integer, np.floating)) and np.isfinite(sigma) and sigma > 0):
        raise InputError(f"sigma must be a positive distance in metres, got {sigma!r}")
    std = np.maximum(float(sigma), np.abs(closest_body_points(points, body, device=device).distance))
    return _diffused_field(points, body, field, std, _sample_offsets(int(num_samples), int(seed)), device)


# --------------------------------------------------------------------------- smoothing on the garment
def laplacian_smooth(values, faces, *, iterations: int = DEFAULT_SMOOTHING_ITERATIONS,
                     step: float = SMOOTHING_STEP) -> np.ndarray:
    """Explicit uniform-Laplacian smoothing of per-vertex values on a triangle mesh.

    values, shape (V, K); faces, int shape (F, 3). Each iteration replaces a vertex's value by
    (1 - step) * its value + step * the mean of its edge neighbours' values. Every update is a convex
    combination, so non-negative rows stay non-negative and rows summing to 1 keep summing to 1
    (cotangent weights would not guarantee that on obtuse triangles). Isolated vertices keep their
    values. Returns a new (V, K) float64 array.
    """
    import scipy.sparse as sp

    from simgen.garment.mesh import unique_edges

    w = np.array(values, dtype=np.float64)
    if iterations <= 0:
        return w
    e = unique_edges(faces)
    nv = len(w)
    adj = sp.coo_matrix((np.ones(2 * len(e)), (np.r_[e[:, 0], e[:, 1]], np.r_[e[:, 1], e[:, 0]])),
                        shape=(nv, nv)).tocsr()
    deg = np.asarray(adj.sum(axis=1)).ravel()
    has = deg > 0
    inv_deg = np.where(has, 1.0 / np.maximum(deg, 1.0), 0.0)
    for _ in range(iterations):
        mean = (adj @ w) * inv_deg[:, None]
        w[has] = (1.0 - step) * w[has] + step * mean[has]
    return w


# --------------------------------------------------------------------------- public: weights
def _check_points(vertices, what: str = "garment vertices") -> np.ndarray:
    v = np.asarray(vertices, dtype=np.float64)
    if v.ndim != 2 or v.shape[1] != 3 or len(v) == 0:
        raise InputError(f"{what} must have shape (V, 3) with V >= 1, got {v.shape}")
    if not np.all(np.isfinite(v)):
        raise InputError(f"{what} contain NaN or inf")
    return v


def _check_faces(faces, num_vertices: int) -> np.ndarray:
    f = np.asarray(faces)
    if f.dtype.kind not in "iu" or f.ndim != 2 or f.shape[1] != 3 or len(f) == 0:
        raise InputError(f"garment faces must be integer indices of shape (F, 3), got {f.shape} {f.dtype}")
    if f.min() < 0 or f.max() >= num_vertices:
        raise InputError(f"garment faces index vertex {int(f.max())} but there are {num_vertices} vertices")
    return f.astype(np.int64)


def compute_skin_weights(vertices, body, *, method: str = "closest", faces=None,
                         num_samples: int = DEFAULT_NUM_SAMPLES, sigma: float = DEFAULT_SIGMA,
                         smoothing_iterations: int = DEFAULT_SMOOTHING_ITERATIONS, seed: int = 0) -> np.ndarray:
    """Linear blend skinning weights of garment vertices, borrowed from the template body.

    Args:
        vertices: garment vertices [m], shape (V, 3), on the template body in rest pose.
        body: the :class:`~simgen.body.BodyModel`; its rest template (``v_template``, ``faces``)
            and ``weights`` (Vb, 24) are used; shape and pose play no part.
        method: ``"closest"``: barycentric blend of the weights of the closest body triangle
            (thesis ch. 4). ``"diffused"``: thesis eq. 6.4, the mean of the closest-point weights
            over Gaussian samples q_n ~ N(p, s(p)^2 I) around each vertex p, with
            s(p) = max(sigma, |d(p)|) and d(p) the distance of p to the body (the thesis uses d
            itself; the floor sigma keeps the average from collapsing to the closest point for
            garments that touch the skin). The same ``num_samples`` standard-normal offsets, drawn
            from ``seed``, serve every vertex (common random numbers), so neighbouring vertices see
            the same sample pattern and the Monte Carlo error varies smoothly over the garment
            instead of as vertex-to-vertex noise. The result is then smoothed on the garment mesh
            with ``smoothing_iterations`` explicit uniform-Laplacian steps (:func:`laplacian_smooth`,
            our addition to eq. 6.4).
        faces: garment triangles, int shape (F, 3); needed for the smoothing of the diffused method.
        num_samples: samples per vertex for "diffused" (rounded up to a multiple of 8: each draw
            is used with the 8 sign patterns of its coordinates, which makes the sample set
            symmetric, so a point on the body's mirror plane gets exactly mirrored weights when
            the body is mirror-symmetric).
        sigma: smallest standard deviation [m] of the samples (default 2 cm).
        smoothing_iterations: Laplacian steps on the garment for "diffused" (0: none).
        seed: seed of the sample offsets; equal inputs and seed give identical weights.

    Returns:
        Weights, shape (V, 24), float64, rows >= 0 summing to 1.

    Cost: "closest" is one BVH query per vertex (0.8 s for 13k points on the open body, CPU);
    "diffused" is num_samples queries per vertex (2.5 s for 4.4k vertices x 64 samples, CPU).
    """
    v = _check_points(vertices)
    if method not in SKINNING_METHODS:
        raise InputError(f"skinning method {method!r} is not one of {', '.join(SKINNING_METHODS)}")
    if faces is not None:
        faces = _check_faces(faces, len(v))
    if method == "closest":
        w = closest_body_points(v, body).blend(body.faces, body.weights)
    else:
        if isinstance(smoothing_iterations, bool) or not isinstance(smoothing_iterations, (int, np.integer)) \
                or smoothing_iterations < 0:
            raise InputError(f"smoothing_iterations must be a non-negative integer, got {smoothing_iterations!r}")
        if smoothing_iterations > 0 and faces is None:
            raise InputError("diffused skinning smooths the weights on the garment mesh: pass faces=, "
                             "or smoothing_iterations=0")
        w = _diffused(v, body, body.weights, num_samples, sigma, seed)
        if smoothing_iterations > 0:
            w = laplacian_smooth(w, faces, iterations=int(smoothing_iterations))
    return _normalise_rows(w)


def _normalise_rows(w: np.ndarray) -> np.ndarray:
    # The body's own rows sum to 1 only to its storage precision (float32 on disk): renormalise.
    w = np.clip(w, 0.0, None)
    s = w.sum(axis=1, keepdims=True)
    if np.any(s <= 0):
        raise InputError("the body's skinning weights are zero at some closest points")
    return w / s


def shape_offsets(vertices, body, betas, *, method: str = "diffused", num_samples: int = DEFAULT_NUM_SAMPLES,
                  sigma: float = DEFAULT_SIGMA, seed: int = 0, device: str | None = "cpu") -> np.ndarray:
    """Displacement [m] that carries garment rest vertices from the template body to shaped bodies.

    Each vertex moves with the body's shape blendshape (v_shaped - v_template) averaged as in
    thesis eq. 6.5 ("diffused", the default; same sampling as :func:`compute_skin_weights`), or
    taken at its closest body point ("closest", barycentric blend). vertices (V, 3); betas (B',)
    or (N, B') -> offsets, shape (N, V, 3). The garment on the shaped rest body is
    vertices + offsets; it is then posed with the shaped body's transforms by :func:`lbs`.

    Why diffused by default: the closest body point jumps where a garment spans a concave region
    (between the legs, under the arms, across the belly), and so does the closest-point offset.
    On the open body's templates at betas of +-2 the closest transfer stretches single edges by up
    to 2x (T-shirt, pants) and 5.8x (dress); the diffused one by at most 1.6x.

    device: the Warp device of the body queries (a GPU answers the diffused method's 64 queries per
    vertex in milliseconds, the CPU in about a second for a T-shirt; the closest faces of two
    devices may differ where a point is as near to two faces, which the blend does not see).
    """
    v = _check_points(vertices)
    b = body.check_betas(betas)  # (N, B)
    if method not in SKINNING_METHODS:
        raise InputError(f"shape offset method {method!r} is not one of {', '.join(SKINNING_METHODS)}")
    nb = body.num_betas
    if nb == 0 or not np.any(b):
        return np.zeros((len(b), len(v), 3))
    field = body.shapedirs.reshape(body.num_vertices, 3 * nb)
    if method == "closest":
        dirs = closest_body_points(v, body, device=device).blend(body.faces, field)
    else:
        dirs = _diffused(v, body, field, num_samples, sigma, seed, device)
    return np.einsum("vcb,nb->nvc", dirs.reshape(len(v), 3, nb), b)


# --------------------------------------------------------------------------- public: skinning
def _check_lbs_args(skin_weights, transforms) -> tuple[np.ndarray, np.ndarray]:
    w = np.asarray(skin_weights, dtype=np.float64)
    if w.ndim != 2 or w.shape[1] != 24:
        raise InputError(f"skin_weights must have shape (V, 24), got {w.shape}")
    a = np.asarray(transforms, dtype=np.float64)
    if a.ndim == 3:
        a = a[None]
    if a.ndim != 4 or a.shape[1:] != (24, 4, 4):
        raise InputError(f"transforms must have shape (N, 24, 4, 4), got {a.shape}")
    return w, a


def _match_frames(x, name: str, w: np.ndarray, a: np.ndarray) -> tuple[np.ndarray, np.ndarray, int]:
    """Points (V, 3) or (N, V, 3) and transforms (N', 24, 4, 4) with N, N' equal or 1: both as
    frame-indexable arrays (a single frame broadcast) and the common frame count."""
    x = np.asarray(x, dtype=np.float64)
    if x.ndim == 2:
        x = x[None]
    n = max(len(a), len(x)) if x.ndim == 3 else len(a)
    if x.ndim != 3 or x.shape[1:] != (len(w), 3) or x.shape[0] not in (1, n) or len(a) not in (1, n):
        raise InputError(f"{name} must have shape ({len(w)}, 3) or (N, {len(w)}, 3) with N = {len(a)} frames "
                         f"of transforms, got {x.shape}")
    return np.broadcast_to(x, (n,) + x.shape[1:]), np.broadcast_to(a, (n,) + a.shape[1:]), n


def _blended(w: np.ndarray, a: np.ndarray) -> np.ndarray:
    """Per-vertex blended transforms sum_j w_vj A_j without the last row, shape (n, V, 3, 4)."""
    n = len(a)
    return np.matmul(w, np.ascontiguousarray(a[:, :, :3, :]).reshape(n, 24, 12)).reshape(n, len(w), 3, 4)


def lbs(vertices_rest, skin_weights, transforms) -> np.ndarray:
    """Linear blend skinning of garment vertices with the body's skinning transforms.

    Args:
        vertices_rest: rest positions [m], shape (V, 3) (one rest shape for all frames) or
            (N, V, 3) (one per frame; N transforms, or one set of transforms for all). They must
            be in the rest space of the body whose transforms are given: the template body for
            betas = 0, the shaped rest body otherwise (add :func:`shape_offsets` first).
        skin_weights: shape (V, 24), rows summing to 1.
        transforms: skinning transforms, shape (N, 24, 4, 4) (or (24, 4, 4)), as returned by
            ``body.forward(betas, pose, trans).transforms``: joint j maps shaped-rest points to posed
            world points, root translation included.

    Returns:
        Posed positions [m], shape (N, V, 3), float64:
        x_posed = (sum_j w_j A_j) [x_rest; 1]. At zero pose A_j = [I | trans], so the rest vertices
        come back translated by trans.
    """
    w, a = _check_lbs_args(skin_weights, transforms)
    x, a, n = _match_frames(vertices_rest, "vertices_rest", w, a)
    out = np.empty((n, len(w), 3))
    for start in range(0, n, _FRAME_CHUNK):
        sl = slice(start, min(start + _FRAME_CHUNK, n))
        t = _blended(w, a[sl])
        out[sl] = np.einsum("nvab,nvb->nva", t[..., :3], x[sl]) + t[..., 3]
    return out


def inverse_lbs(posed, skin_weights, transforms) -> np.ndarray:
    """Undo linear blend skinning: the rest positions that :func:`lbs` maps to ``posed``.

    Args:
        posed: posed positions [m], shape (N, V, 3) (or (V, 3) for one frame).
        skin_weights: shape (V, 24).
        transforms: shape (N, 24, 4, 4) (or one set (24, 4, 4) for all frames), the same
            skinning transforms as for :func:`lbs`.

    Returns:
        Rest positions [m], shape (N, V, 3): x_rest = M_v^-1 (x_posed - t_v) with [M_v | t_v] =
        sum_j w_j A_j, each vertex's blended transform inverted exactly (a solve of its 3x3 linear
        part). This is the unposing of thesis eq. 4.5. The blended linear part is singular only
        for weights split between joints rotated about half a turn apart; InputError then.
    """
    w, a = _check_lbs_args(skin_weights, transforms)
    y, a, n = _match_frames(posed, "posed", w, a)
    out = np.empty((n, len(w), 3))
    for start in range(0, n, _FRAME_CHUNK):
        sl = slice(start, min(start + _FRAME_CHUNK, n))
        t = _blended(w, a[sl])
        try:
            out[sl] = np.linalg.solve(t[..., :3], (y[sl] - t[..., 3])[..., None])[..., 0]
        except np.linalg.LinAlgError:
            raise InputError("inverse_lbs: a vertex's blended skinning transform is singular "
                             "(its weights mix joints rotated about half a turn apart)") from None
    return out
