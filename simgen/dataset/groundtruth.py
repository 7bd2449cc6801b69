"""Ground truth of the garment fit and wrinkle regressors (thesis ch. 4, eqs. 4.2 to 4.5), numpy float64.

The learned garment is  M_c(beta, theta) = W(T_c + Delta_G(beta) + Delta_L(beta, theta), beta, theta, W_c)
(eqs. 4.2, 4.3) with W linear blend skinning by the body's joint transforms A(beta, theta) and the
garment's skinning weights W_c. From the simulations:

- template T_c = rho(T_r): the garment relaxed once on the template body (betas 0, rest pose), T_r,
  smoothed by the operator rho (:func:`smooth_garment`);
- fit displacement (eq. 4.4)  Delta_G = rho(S_c(beta, 0)) - T_c, S_c(beta, 0) the garment simulated
  on the shaped body in rest pose without root translation (:func:`fit_displacement`);
- wrinkle displacement (eq. 4.5)  Delta_L = W^-1(S_c(beta, theta), beta, theta, W_c) - T_c - Delta_G,
  the simulated frame unposed by inverting each vertex's blended skinning transform
  (:func:`wrinkle_displacements`); :func:`reconstruct` is its exact inverse.

At theta = 0 and no translation A(beta, 0) is the identity for every joint (SMPL's transforms
remove the rest joint positions), so the rest-pose fit lives in the same unposed space as the
unposed frames, and Delta_L of the fit simulation itself is S_c - rho(S_c): the detail that the
smoothing leaves to the wrinkle model.

The smoothing rho (not specified in the thesis; chosen here) is Taubin's lambda|mu smoothing with
the uniform ("umbrella") Laplacian on the garment mesh: each iteration moves every vertex by
lambda * L(x) and then by mu * L(x), mu < -lambda, which removes wrinkles (high spatial frequencies)
without the shrinkage of plain Laplacian smoothing. Defaults: 10 iterations, lambda = 0.5,
mu = -0.53 (pass band k_PB = 1/lambda + 1/mu ~ 0.11). Boundary vertices (hems, neck, sleeve ends)
are smoothed along their boundary loop only, so openings keep their place and shape instead of
being pulled into the garment.
"""

from __future__ import annotations

import functools
from dataclasses import asdict, dataclass

import numpy as np

from simgen.body.model import skinning_transforms
from simgen.errors import InputError

__all__ = [
    "SmoothingParams", "smooth_garment", "fit_displacement", "skinning_transforms", "wrinkle_displacements",
    "reconstruct", "SMOOTHING_METHODS",
]

SMOOTHING_METHODS = ("taubin", "laplacian", "none")
_BOUNDARY_MODES = ("boundary", "free", "fixed")


@dataclass(frozen=True)
class SmoothingParams:
    """Parameters of the smoothing operator rho (eq. 4.4) on the garment mesh.

    method: "taubin" (lambda then mu steps, volume-preserving in the mean), "laplacian" (lambda steps
      only: shrinks) or "none" (identity).
    iterations: number of (lambda, mu) step pairs.
    lam: the positive step lambda in (0, 1]; mu: the negative step, mu < -lam for "taubin".
    boundary: "boundary" (boundary vertices use only their boundary-loop neighbours), "free" (all
      edge neighbours) or "fixed" (boundary vertices do not move).
    """

    method: str = "taubin"
    iterations: int = 10
    lam: float = 0.5
    mu: float = -0.53
    boundary: str = "boundary"

    def __post_init__(self) -> None:
        if self.method not in SMOOTHING_METHODS:
            raise InputError(f"smoothing method must be one of {', '.join(SMOOTHING_METHODS)}, got {self.method!r}")
        if isinstance(self.iterations, bool) or not isinstance(self.iterations, (int, np.integer)) \
                or self.iterations < 0:
            raise InputError(f"smoothing iterations must be an integer >= 0, got {self.iterations!r}")
        if not (0.0 < float(self.lam) <= 1.0):
            raise InputError(f"smoothing lam must be in (0, 1], got {self.lam!r}")
        if self.method == "taubin" and not float(self.mu) < -float(self.lam):
            raise InputError(f"smoothing mu must be below -lam for Taubin smoothing, got {self.mu!r}")
        if self.boundary not in _BOUNDARY_MODES:
            raise InputError(f"smoothing boundary must be one of {', '.join(_BOUNDARY_MODES)}, got {self.boundary!r}")

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> SmoothingParams:
        return cls(**d)


def _vertices(x, what: str) -> np.ndarray:
    a = np.asarray(x, dtype=np.float64)
    if a.ndim != 2 or a.shape[1] != 3:
        raise InputError(f"{what} must have shape (V, 3), got {a.shape}")
    return a


def _umbrella_operator(faces: np.ndarray, num_vertices: int, boundary: str):
    """Neighbour pairs (rows, cols), inverse degrees (V,) and a mask of vertices that move, so that
    the umbrella Laplacian is L(x)_i = mean of x over the cols of row i, minus x_i (numpy only:
    nothing beyond numpy is needed where datasets are generated)."""
    from simgen.garment.mesh import edge_face_counts

    f = np.asarray(faces, dtype=np.int64)
    if f.ndim != 2 or f.shape[1] != 3 or len(f) == 0:
        raise InputError(f"faces must have shape (F, 3), got {f.shape}")
    if f.min() < 0 or f.max() >= num_vertices:
        raise InputError(f"faces index vertex {int(f.max())} but there are {num_vertices} vertices")
    edges, counts = edge_face_counts(f)
    bedges = edges[counts == 1]
    on_boundary = np.zeros(num_vertices, dtype=bool)
    on_boundary[bedges.ravel()] = True
    rows = np.r_[edges[:, 0], edges[:, 1]]
    cols = np.r_[edges[:, 1], edges[:, 0]]
    move = np.ones(num_vertices, dtype=bool)
    if boundary == "boundary":
        # Interior rows keep every edge neighbour; boundary rows only their two boundary-loop neighbours.
        keep = ~on_boundary[rows]
        rows = np.r_[rows[keep], bedges[:, 0], bedges[:, 1]]
        cols = np.r_[cols[keep], bedges[:, 1], bedges[:, 0]]
    elif boundary == "fixed":
        move = ~on_boundary
    deg = np.bincount(rows, minlength=num_vertices).astype(np.float64)
    move &= deg > 0
    inv = np.where(deg > 0, 1.0 / np.maximum(deg, 1.0), 0.0)
    return rows, cols, inv, move


@functools.lru_cache(maxsize=8)
def _cached_operator(faces_bytes: bytes, num_faces: int, num_vertices: int, boundary: str):
    faces = np.frombuffer(faces_bytes, dtype=np.int64).reshape(num_faces, 3)
    return _umbrella_operator(faces, num_vertices, boundary)


def smooth_garment(vertices, faces, params: SmoothingParams | None = None) -> np.ndarray:
    """The smoothing operator rho of eq. 4.4 on a garment mesh.

    vertices [m], shape (V, 3); faces, int shape (F, 3); params: :class:`SmoothingParams` (None:
    the defaults). Returns smoothed vertices [m], shape (V, 3), float64. Linear in the vertices
    and translation-equivariant (rho(x + c) = rho(x) + c), so it commutes with the rigid offsets the
    store removes.
    """
    p = params if params is not None else SmoothingParams()
    x = _vertices(vertices, "vertices to smooth").copy()
    if p.method == "none" or p.iterations == 0:
        return x
    f = np.ascontiguousarray(faces, dtype=np.int64)
    rows, cols, inv, move = _cached_operator(f.tobytes(), len(f), len(x), p.boundary)
    steps = [float(p.lam), float(p.mu)] if p.method == "taubin" else [float(p.lam)]
    m = move[:, None]
    n = len(x)
    for _ in range(int(p.iterations)):
        for s in steps:
            mean = np.stack([np.bincount(rows, weights=x[cols, c], minlength=n) for c in range(3)], axis=1)
            x = x + s * np.where(m, mean * inv[:, None] - x, 0.0)
    return x


def fit_displacement(fit_vertices, template_smoothed, faces, params: SmoothingParams | None = None) -> np.ndarray:
    """Eq. 4.4: Delta_G = rho(S_c(beta, 0)) - T_c.

    fit_vertices [m], (V, 3): the garment simulated on the shaped body in rest pose, no root
    translation; template_smoothed [m], (V, 3): T_c; faces (F, 3). Returns (V, 3) float64 [m].
    """
    fit = _vertices(fit_vertices, "fit_vertices")
    tc = _vertices(template_smoothed, "template_smoothed")
    if fit.shape != tc.shape:
        raise InputError(f"fit_vertices {fit.shape} and template_smoothed {tc.shape} differ in shape")
    return smooth_garment(fit, faces, params) - tc


def wrinkle_displacements(garment_vertices, transforms, skin_weights, template_smoothed, fit_disp) -> np.ndarray:
    """Eq. 4.5: Delta_L = W^-1(S_c(beta, theta)) - T_c - Delta_G, frame by frame.

    garment_vertices [m], (T, V, 3): simulated frames; transforms (T, 24, 4, 4) from
    :func:`skinning_transforms` with the frames' betas, poses and trans; skin_weights (V, 24);
    template_smoothed T_c [m], (V, 3); fit_disp Delta_G [m], (V, 3). Returns (T, V, 3) float64 [m].
    """
    from simgen.garment.skinning import inverse_lbs

    tc = _vertices(template_smoothed, "template_smoothed")
    dg = _vertices(fit_disp, "fit_displacement")
    unposed = inverse_lbs(garment_vertices, skin_weights, transforms)
    return unposed - tc[None] - dg[None]


def reconstruct(template_smoothed, fit_disp, wrinkle, transforms, skin_weights) -> np.ndarray:
    """Eqs. 4.2 + 4.3: M_c = W(T_c + Delta_G + Delta_L) per frame, the inverse of :func:`wrinkle_displacements`.

    template_smoothed [m] (V, 3); fit_disp [m] (V, 3); wrinkle [m] (T, V, 3) (or (V, 3) for one
    frame); transforms (T, 24, 4, 4); skin_weights (V, 24). Returns posed positions [m], (T, V, 3) float64.
    """
    from simgen.garment.skinning import lbs

    tc = _vertices(template_smoothed, "template_smoothed")
    dg = _vertices(fit_disp, "fit_displacement")
    w = np.asarray(wrinkle, dtype=np.float64)
    if w.ndim == 2:
        w = w[None]
    if w.ndim != 3 or w.shape[1:] != tc.shape:
        raise InputError(f"wrinkle must have shape (T, {len(tc)}, 3), got {w.shape}")
    return lbs(tc[None] + dg[None] + w, skin_weights, transforms)
