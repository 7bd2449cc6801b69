"""Metric relaxation of predicted garments: projective dynamics on the triangles' rest metric, in torch.

A learned garment model predicts every vertex independently of its neighbours, so its regression
errors (a few mm against 1.5 cm edges) strain the triangles: each one is stretched, sheared or
compressed against its rest shape. The collision post-process (:func:`simgen.learn.collision.push_out`)
moves vertices out of the body but leaves that metric as it is. :class:`MetricRelax` restores it: it
finds the positions x [m] (N, V, 3) closest to the prediction p whose triangles keep their rest
shape, by minimising

    E(x) = sum_t a_t ||F_t(x) - R_t||_F^2  +  fidelity * sum_v m_v ||x_v - p_v||^2        [m^2]

- F_t (3, 2) = [x1 - x0, x2 - x0] Dm_t^-1: the deformation gradient of triangle t, Dm_t^-1 (2, 2)
  [1/m] its inverse rest shape in its own 2D frame (:func:`simgen.physics.rest.triangle_rest_frames`);
  a_t [m^2] its rest area; R_t the 3x2 matrix with orthonormal columns closest to F_t (its polar
  factor): the membrane ("as-rigid-as-possible") term is zero exactly for rigid motions of each
  triangle and measures stretch, compression and shear alike;
- m_v [m^2] = sum of a_t / 3 over the triangles at v: the lumped vertex area; fidelity [1/m^2]
  weighs the tie to the prediction (large: stay at p; small: restore the metric, p only fixes the
  rigid motion and what the metric leaves free, e.g. bending).

The minimisation is projective dynamics (Bouaziz, Martin, Liu, Kavan, Pauly 2014, "Projective
Dynamics: Fusing Constraint Projections for Fast Simulation", without the inertia term), alternating

- the local step: R_t = F_t (F_t^T F_t)^(-1/2) per triangle, by the closed form of a 2x2 SPD
  matrix's inverse square root (:func:`polar_factor`);
- the global step: the minimiser over x for fixed R, the linear system A x = b with the constant
  sparse V x V matrix A = sum_t a_t S_t^T D_t^T D_t S_t + fidelity diag(m) (D_t = Dm_t^-T [[-1, 1, 0],
  [-1, 0, 1]] (2, 3) maps the triangle's vertices to F_t^T, S_t selects them), the same for x, y and z,
  and b = sum_t a_t S_t^T D_t^T R_t^T + fidelity diag(m) p. A is SPD and factored once per device: on
  the CPU a sparse LU (SciPy's SuperLU; two triangular solves per step), on a GPU its dense inverse
  (float64 Cholesky there), so that a step is one (V, V) @ (V, 3N) product for all N frames, with no
  host synchronisation.

Each plain step lowers E, so E never rises over plain iterations (without contacts). The
iterations are accelerated by Chebyshev's semi-iterative method as Wang (2015, "A Chebyshev
Semi-Iterative Approach for Accelerating Projective and Position-based Dynamics") does for PD:
x_{k+1} = omega_k (y_{k+1} - x_{k-1}) + x_{k-1}, y_{k+1} the plain step from x_k, with weights from an
estimate rho of the plain iteration's spectral radius (:func:`chebyshev_weights`); the fixed point is
the same without contacts, reached in fewer iterations, but E may rise on the way. With contacts
the overshoot can carry vertices across other planes before those are renewed: on a test sheet
over a sphere rho 0.95 ends where plain steps do, rho 0.99 stops at 8x their energy. The defaults
(16 iterations, rho 0.95, fidelity 10 m^-2) were chosen on held-out sequences of the
thesis-tshirt model (BENCHMARKS.md, "The metric post-process's settings").

Contacts: the body is queried at the start and every ``CONTACT_REFRESH`` iterations
(:meth:`CollisionSurface.query`; the cloth slides as its metric returns, and planes of the start
would let vertices outside the band at the start sink in). Every vertex whose signed distance d is
below ``clearance + contact_band`` keeps the tangent plane through its closest point c = x - d n
(n the outward unit normal), and after every global step it is projected onto the half-space
``clearance`` outside that plane: x <- x + max(0, clearance - (x - c).n) n. A final
:func:`~simgen.learn.collision.push_out` leaves no vertex closer than ``clearance`` to the body (the
planes only approximate the body near the positions of the last query).

Cost per iteration: one batched 2x2 closed form per triangle and the global solve. On a GPU the dense
inverse holds V^2 entries (77 MB at V = 4399 in float32), read once per iteration; there is no
Python loop over triangles or vertices and no host synchronisation between two contact queries (a
query checks its result on the host), so for one frame on a GPU each such stretch is replayed from
a CUDA graph (a frame's few hundred small kernels take longer to launch from Python than to run);
batches of frames run eagerly. A dense inverse on the CPU would read those 78 MB per iteration at
memory speed (tens of ms), hence the sparse factor there.
"""

from __future__ import annotations

import math
import weakref

import numpy as np
import scipy.sparse
import scipy.sparse.linalg
import torch

from simgen.errors import InputError
from simgen.learn.collision import DEFAULT_CLEARANCE, CollisionSurface, MeshSpread, push_out
from simgen.physics.rest import triangle_rest_frames

__all__ = ["MetricRelax", "PUSH_TOLERANCE", "chebyshev_weights", "polar_factor"]

#: [m] A final push shorter than this does not count a vertex as moved: rounding at the planes, which
#: reaches ~1e-7 m in float32 (a GPU's default), where matrix products may round differently per call.
PUSH_TOLERANCE = 1e-6

#: Plain local/global steps before the Chebyshev weights start (the fast modes settle first).
CHEBYSHEV_DELAY = 2

#: Iterations between queries of the body for the contact planes (the first at the start).
CONTACT_REFRESH = 8

# F^T = D X for the triangle's vertex rows X (3, 3): the edge operator [[-1, 1, 0], [-1, 0, 1]].
_EDGES = ((-1.0, 1.0, 0.0), (-1.0, 0.0, 1.0))


def chebyshev_weights(iterations: int, spectral_radius: float, delay: int = CHEBYSHEV_DELAY) -> tuple:
    """The weights omega_k (k = 0 .. iterations - 1) of Chebyshev semi-iterative acceleration (Wang 2015,
    "A Chebyshev Semi-Iterative Approach for Accelerating Projective and Position-based Dynamics"):
    x_{k+1} = omega_k (y_{k+1} - x_{k-1}) + x_{k-1}, y_{k+1} the plain local/global step from x_k.
    1 for the first ``delay`` iterations (and all of them for spectral_radius 0: plain steps), then
    2 / (2 - rho^2), then omega <- 4 / (4 - rho^2 omega), rho the spectral radius [-] in [0, 1)."""
    rho2, out, omega = float(spectral_radius) ** 2, [], 1.0
    for k in range(iterations):
        if rho2 > 0.0 and k >= delay:
            omega = 2.0 / (2.0 - rho2) if k == delay else 4.0 / (4.0 - rho2 * omega)
        out.append(omega)
    return tuple(out)


def polar_factor(ft: torch.Tensor) -> torch.Tensor:
    """The transposed polar factor R^T (..., 2, 3) of deformation gradients given as F^T (..., 2, 3).

    R = F C^(-1/2), C = F^T F (2x2 SPD), closest to F among 3x2 matrices with orthonormal columns
    (dimensionless). Closed form: with s = sqrt(det C) = |f1 x f2| (f1, f2 the columns of F; computed
    as a cross product, so never negative), sqrt(C) = (C + s I) / sqrt(tr C + 2 s) and
    C^(-1/2) = adj(C + s I) / (s sqrt(tr C + 2 s)). s is clamped to the dtype's epsilon, so a collapsed
    triangle (F = 0) gets R = 0 and a collinear one (rank-1 F = sigma u v^T) R ~ u v^T: finite, and
    exact for every triangle whose area ratio s exceeds the epsilon.
    """
    f1, f2 = ft[..., 0, :], ft[..., 1, :]
    c00, c11, c01 = (f1 * f1).sum(-1), (f2 * f2).sum(-1), (f1 * f2).sum(-1)
    s = torch.linalg.cross(f1, f2, dim=-1).norm(dim=-1).clamp(min=torch.finfo(ft.dtype).eps)
    scale = 1.0 / (s * (c00 + c11 + 2.0 * s).sqrt())
    adj = torch.stack([torch.stack([c11 + s, -c01], -1), torch.stack([-c01, c00 + s], -1)], -2)
    return (adj * scale[..., None, None]) @ ft


class MetricRelax:
    """Restores the rest metric of predicted garment triangles near the prediction (module doc).

    rest_positions [m] (V, 3): the garment's rest shape (template); faces (F, 3) int: its triangles
    (every vertex in one at least, no triangle degenerate at rest); fidelity [1/m^2] > 0: the tie to
    the prediction; iterations >= 1: local/global/contact rounds; spectral_radius [-] in [0, 1): the
    Chebyshev acceleration's estimate (0: plain steps); contact_band [m] >= 0: vertices
    within ``clearance + contact_band`` of the body at a query get a contact plane. Tensors are
    stored in ``dtype`` on ``device``, with the global matrix's factor for that device (module doc).
    """

    def __init__(self, rest_positions, faces, *, fidelity: float = 10.0, iterations: int = 16,
                 spectral_radius: float = 0.95, contact_band: float = 0.01, device=None,
                 dtype: torch.dtype = torch.float32) -> None:
        rest, f = _check_mesh(rest_positions, faces)
        if not (math.isfinite(float(fidelity)) and float(fidelity) > 0):
            raise InputError(f"fidelity must be a finite number > 0 [1/m^2], got {fidelity}")
        if isinstance(iterations, bool) or int(iterations) != iterations or iterations < 1:
            raise InputError(f"iterations must be an integer >= 1, got {iterations}")
        if not (math.isfinite(float(contact_band)) and float(contact_band) >= 0):
            raise InputError(f"contact_band must be a finite distance >= 0 [m], got {contact_band}")
        if not 0.0 <= float(spectral_radius) < 1.0:
            raise InputError(f"spectral_radius must be in [0, 1), got {spectral_radius}")
        self.weights = chebyshev_weights(int(iterations), spectral_radius)
        self.fidelity, self.iterations, self.contact_band = float(fidelity), int(iterations), float(contact_band)
        self.dtype = dtype
        inv_rest, area = triangle_rest_frames(rest, f)
        d = inv_rest.transpose(1, 2) @ torch.tensor(_EDGES, dtype=torch.float64)       # (F, 2, 3) [1/m]
        corner_area = (area / 3.0).repeat_interleave(3)
        mass = torch.zeros(len(rest), dtype=torch.float64).index_add_(0, f.reshape(-1), corner_area)
        self.matrix = _assemble(d, area, mass, f, self.fidelity)   # A (V, V) [-], SciPy CSR, float64
        self.faces = f
        self.grad_op = d                                        # D_t (F, 2, 3) [1/m]
        self.area = area                                        # a_t (F,) [m^2]
        self.weighted_grad_t = area[:, None, None] * d.transpose(1, 2)   # a_t D_t^T (F, 3, 2) [m]
        self.tie = self.fidelity * mass                         # fidelity m_v (V,) [-]
        self._device, self._lu, self.ainv = None, None, None
        self.to(device if device is not None else "cpu")

    @property
    def num_vertices(self) -> int:
        return int(self.matrix.shape[0])

    @property
    def device(self) -> torch.device:
        return self._device

    def to(self, device) -> "MetricRelax":
        """Move the stored tensors to ``device`` (in place, floating ones in ``self.dtype``) with the
        global matrix factored for it: a sparse LU on the CPU, the dense inverse on a GPU; returns self."""
        device = torch.device(device)
        if device.type == "cuda" and device.index is None:     # tensors on "cuda" report their index
            device = torch.device("cuda", torch.cuda.current_device())
        self.faces = self.faces.to(device)
        for name in ("grad_op", "area", "weighted_grad_t", "tie"):
            setattr(self, name, getattr(self, name).to(device=device, dtype=self.dtype))
        if device != self._device:
            self._lu = scipy.sparse.linalg.splu(self.matrix.tocsc()) if device.type == "cpu" else None
            self.ainv = None if device.type == "cpu" else _dense_inverse(self.matrix, device).to(self.dtype)
        self._graphs = _SegmentGraphs(self)    # recorded graphs read the tensors set above
        self._device = device
        return self

    # -- use ------------------------------------------------------------------------------------

    @torch.no_grad()
    def __call__(self, points: torch.Tensor, body_vertices: torch.Tensor, surface: CollisionSurface, *,
                 clearance: float = DEFAULT_CLEARANCE,
                 spread: MeshSpread | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """Relax predicted garments towards their rest metric, then push them out of the body.

        points [m] (N, V, 3) or (V, 3): the prediction p; body_vertices [m] of the posed body
        (N, B, 3) or (B, 3); surface: the body's :class:`CollisionSurface`; clearance [m]: the distance
        outside the body at which contacts end; spread: the garment's :class:`MeshSpread` for the final
        push (see :func:`push_out`). Returns (points [m] of the input's shape, dtype and device, moved
        (bool, (N, V) or (V,)): the vertices closer than ``clearance`` to the body at the start or
        that the final push moved by more than PUSH_TOLERANCE).
        """
        p, single = self._frames(points, "points")
        body = self._body(body_vertices, surface, len(p))
        relaxed, touching = self._relax(p, body, surface, clearance)
        x, _ = push_out(relaxed, body, surface, clearance=clearance, spread=spread)
        # Not push_out's flags: a vertex the planes left exactly at clearance may read a hair closer.
        pushed = (x - relaxed).norm(dim=-1) > PUSH_TOLERANCE
        out, moved = x.to(points.dtype), touching | pushed
        return (out[0], moved[0]) if single else (out, moved)

    @torch.no_grad()
    def energy(self, points: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
        """E(x) [m^2] of the module doc per frame, (N,) (or () for (V, 3) input), for positions
        points = x [m] (N, V, 3) or (V, 3) tied to the prediction target = p [m] of the same shape."""
        x, single = self._frames(points, "points")
        p, _ = self._frames(target, "target")
        if p.shape != x.shape:
            raise InputError(f"target must have the shape of points {tuple(points.shape)}, got {tuple(target.shape)}")
        ft = self._deformation_t(x)
        membrane = (self.area * ((ft - polar_factor(ft)) ** 2).sum((-2, -1))).sum(-1)
        tie = (self.tie[:, None] * (x - p) ** 2).sum((-2, -1))
        e = membrane + tie
        return e[0] if single else e

    # -- steps ----------------------------------------------------------------------------------

    def _relax(self, p: torch.Tensor, body: torch.Tensor, surface: CollisionSurface,
               clearance: float) -> tuple[torch.Tensor, torch.Tensor]:
        """The PD iterations from x = p [m] (N, V, 3) with contact planes of the start, renewed every
        CONTACT_REFRESH iterations: (x [m] (N, V, 3) before the final push, touching (N, V) bool:
        closer than ``clearance`` at the start). One frame on a GPU replays each stretch between two
        queries from a CUDA graph (:class:`_SegmentGraphs`)."""
        q = surface.query(p, body)
        touching = q.distance < clearance
        x_prev, x = p, p
        for start in range(0, self.iterations, CONTACT_REFRESH):
            if start:
                q = surface.query(x, body)
            planes = _contact_planes(x, q.distance, q.normal, clearance, self.contact_band)
            stop = min(start + CONTACT_REFRESH, self.iterations)
            if self._device.type == "cuda" and len(p) == 1:
                x_prev, x = self._graphs.run(start, stop, x_prev, x, p, *planes)
            else:
                x_prev, x = self._iterate(start, stop, x_prev, x, p, *planes)
        return x, touching

    def _iterate(self, start: int, stop: int, x_prev, x, p, normal, level, contact):
        """Iterations start .. stop - 1 from (x_{k-1}, x_k) [m] (N, V, 3) with fixed contact planes:
        the plain step, the Chebyshev weight, the planes' projection; returns the last two iterates."""
        for k in range(start, stop):
            y = self._global_step(polar_factor(self._deformation_t(x)), p)
            omega = self.weights[k]
            if omega != 1.0:
                y = omega * (y - x_prev) + x_prev
            x_prev, x = x, _project_contacts(y, normal, level, contact)
        return x_prev, x

    def _deformation_t(self, x: torch.Tensor) -> torch.Tensor:
        """F_t^T (N, F, 2, 3) (dimensionless) of every triangle for positions x [m] (N, V, 3)."""
        corners = x[:, self.faces]                              # (N, F, 3, 3): rows x0, x1, x2
        return self.grad_op @ corners

    def _global_step(self, rt: torch.Tensor, p: torch.Tensor) -> torch.Tensor:
        """argmin_x E(x; R) [m] (N, V, 3) for the rotations given as R_t^T (N, F, 2, 3) and p [m] (N, V, 3)."""
        per_corner = self.weighted_grad_t @ rt                 # a_t D_t^T R_t^T (N, F, 3, 3) [m]
        # Solved for x - c, c the prediction's centroid per frame (exact: the membrane rows of A sum to
        # zero, so A c = fidelity m c), which keeps a float32 solve as precise far from the origin.
        c = p.mean(dim=1, keepdim=True)
        b = (self.tie[:, None] * (p - c)).index_add(1, self.faces.reshape(-1), per_corner.flatten(1, 2))
        n, v, _ = b.shape      # all frames' coordinates as the columns of one right-hand side
        rhs = b.permute(1, 0, 2).reshape(v, 3 * n)
        if self._lu is not None:
            x = torch.from_numpy(self._lu.solve(rhs.double().numpy())).to(rhs.dtype)
        else:
            x = self.ainv @ rhs
        return c + x.reshape(v, n, 3).permute(1, 0, 2)

    # -- inputs ---------------------------------------------------------------------------------

    def _frames(self, x, what: str) -> tuple[torch.Tensor, bool]:
        """x as (N, V, 3) in this relax's dtype, and whether it came as one frame (V, 3)."""
        if not isinstance(x, torch.Tensor) or not x.is_floating_point():
            raise InputError(f"{what} must be a floating-point torch tensor of shape (N, V, 3) or (V, 3)")
        if x.ndim not in (2, 3) or x.shape[-2:] != (self.num_vertices, 3):
            raise InputError(f"{what} must have shape (N, {self.num_vertices}, 3) or ({self.num_vertices}, 3), "
                             f"got {tuple(x.shape)}")
        if x.device != self.device:
            raise InputError(f"{what} is on {x.device} but the relax's matrices are on {self.device}")
        single = x.ndim == 2
        return (x[None] if single else x).to(self.dtype), single

    def _body(self, body_vertices, surface: CollisionSurface, frames: int) -> torch.Tensor:
        """body_vertices as (N, B, 3) in this relax's dtype ((B, 3): the same body for all N frames)."""
        b = torch.as_tensor(body_vertices)
        b = b[None].expand(frames, -1, -1) if b.ndim == 2 else b
        if b.ndim != 3 or b.shape[1:] != (surface.num_vertices, 3) or b.shape[0] != frames:
            raise InputError(f"body_vertices must have shape ({frames}, {surface.num_vertices}, 3) or "
                             f"({surface.num_vertices}, 3) for {frames} frame(s) of points, got {tuple(b.shape)}")
        return b.to(device=self.device, dtype=self.dtype)


class _SegmentGraphs:
    """CUDA graphs of :meth:`MetricRelax._iterate` for one frame, one per stretch (start, stop)
    between two contact queries: a frame's iterations are a few hundred small kernels, launched from
    Python in more time than they run. The first call of a stretch warms it up on a side stream and
    records it; every call copies its inputs into the recording's buffers, replays it and returns
    copies of the two iterates (the eager ones to float rounding: tests/test_learn_relax.py on a
    GPU). A graph reads the relax's tensors as they were when it was recorded: ``MetricRelax.to``
    starts a new set."""

    def __init__(self, relax: MetricRelax) -> None:
        self.relax = weakref.proxy(relax)   # the relax holds this object: no reference cycle
        self.graphs: dict = {}

    def run(self, start: int, stop: int, *inputs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """inputs: x_prev, x, p [m] (1, V, 3), normal (1, V, 3), level [m] (1, V), contact (1, V) bool."""
        key = (start, stop, tuple(tuple(t.shape) for t in inputs), inputs[0].dtype)
        with torch.cuda.device(inputs[0].device):    # capture and replay on the relax's GPU
            if key not in self.graphs:
                self.graphs[key] = self._record(start, stop, inputs)
            graph, buffers, outputs = self.graphs[key]
            for buf, t in zip(buffers, inputs):
                buf.copy_(t)
            graph.replay()
            return outputs[0].clone(), outputs[1].clone()

    def _record(self, start: int, stop: int, inputs) -> tuple:
        buffers = tuple(t.clone() for t in inputs)
        device = buffers[0].device
        side = torch.cuda.Stream(device=device)
        side.wait_stream(torch.cuda.current_stream(device))
        with torch.cuda.stream(side):   # warm-up (cuBLAS and the allocator settle before recording)
            self.relax._iterate(start, stop, *buffers)
        torch.cuda.current_stream(device).wait_stream(side)
        graph = torch.cuda.CUDAGraph()
        with torch.cuda.graph(graph):
            outputs = self.relax._iterate(start, stop, *buffers)
        return graph, buffers, outputs


def _check_mesh(rest_positions, faces) -> tuple[torch.Tensor, torch.Tensor]:
    """rest_positions [m] as float64 (V, 3) and faces as int64 (F, 3) (CPU), validated."""
    v = np.asarray(rest_positions.detach().cpu() if torch.is_tensor(rest_positions) else rest_positions,
                   dtype=np.float64)
    f = np.asarray(faces.detach().cpu() if torch.is_tensor(faces) else faces)
    if v.ndim != 2 or v.shape[1] != 3 or len(v) < 3 or not np.all(np.isfinite(v)):
        raise InputError(f"rest_positions must be finite of shape (V, 3) with V >= 3, got shape {v.shape}")
    if f.ndim != 2 or f.shape[1] != 3 or len(f) == 0 or not np.issubdtype(f.dtype, np.integer):
        raise InputError(f"faces must be integers of shape (F, 3), got {f.dtype} {f.shape}")
    if f.min() < 0 or f.max() >= len(v):
        raise InputError(f"faces index vertices {int(f.min())}..{int(f.max())} of rest_positions' {len(v)}")
    unused = np.setdiff1d(np.arange(len(v)), f.reshape(-1))
    if len(unused):
        raise InputError(f"rest_positions vertex {int(unused[0])} belongs to no face (its row of A would be zero)")
    return torch.as_tensor(v), torch.as_tensor(f.astype(np.int64))


def _assemble(d: torch.Tensor, area: torch.Tensor, mass: torch.Tensor, faces: torch.Tensor,
              fidelity: float) -> scipy.sparse.csr_matrix:
    """The global matrix A (V, V) (dimensionless) = sum_t a_t S_t^T D_t^T D_t S_t + fidelity diag(m),
    float64 CSR, from D_t (F, 2, 3) [1/m], a_t (F,) [m^2], m (V,) [m^2] and faces (F, 3)."""
    k = area[:, None, None] * (d.transpose(1, 2) @ d)          # (F, 3, 3) per-triangle blocks
    rows = faces[:, :, None].expand(-1, 3, 3).reshape(-1).numpy()
    cols = faces[:, None, :].expand(-1, 3, 3).reshape(-1).numpy()
    v = len(mass)
    blocks = scipy.sparse.coo_matrix((k.reshape(-1).numpy(), (rows, cols)), shape=(v, v))   # duplicates summed
    return (blocks + scipy.sparse.diags(fidelity * mass.numpy())).tocsr()


def _dense_inverse(matrix: scipy.sparse.csr_matrix, device: torch.device) -> torch.Tensor:
    """A^-1 (V, V) float64 on ``device`` of the SPD matrix A, by a Cholesky factor there."""
    a = torch.as_tensor(matrix.toarray(), device=device)
    return torch.cholesky_inverse(torch.linalg.cholesky(a))


def _contact_planes(x: torch.Tensor, distance: torch.Tensor, normal: torch.Tensor, clearance: float,
                    band: float) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Contact half-spaces of the vertices x [m] (N, V, 3) at signed distance [m] (N, V) with outward
    normal (N, V, 3): (normal, level [m] (N, V) = c.n + clearance for the closest point c = x - d n,
    contact (N, V) bool: d < clearance + band). A vertex y is outside its half-space when y.n >= level."""
    closest = x - distance[..., None] * normal
    level = (closest * normal).sum(-1) + clearance
    return normal.to(x.dtype), level, distance < clearance + band


def _project_contacts(x: torch.Tensor, normal: torch.Tensor, level: torch.Tensor,
                      contact: torch.Tensor) -> torch.Tensor:
    """x [m] (N, V, 3) with each contact vertex moved along its plane normal onto its half-space."""
    depth = torch.where(contact, (level - (x * normal).sum(-1)).clamp(min=0.0), torch.zeros_like(level))
    return x + depth[..., None] * normal
