"""MetricRelax (simgen.learn.relax): projective dynamics restoring the rest metric of a predicted
garment, held to the prediction, with contact planes and the final collision push-out. Small sheets
(10 x 10 vertices, 0.2 m) and an icosphere body, on the CPU, float64 where exactness matters."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse
import scipy.sparse.linalg
import torch
import trimesh

from simgen.errors import InputError
from simgen.learn.collision import CollisionSurface, push_out
from simgen.learn.relax import PUSH_TOLERANCE, MetricRelax, chebyshev_weights
from simgen.physics import ClothRest
from simgen.physics.membrane import green_strain

CLEARANCE = 0.002
F64 = torch.float64
FAR = np.array([0.0, 0.0, 2.0])        # 1.7 m above the sphere: no contact


def _sheet(n=10, size=0.2, bump=0.0):
    """A grid sheet of n x n vertices over size x size [m] in the xy plane (z = bump * a smooth hill),
    triangulated; returns (vertices (n^2, 3), faces (2 (n-1)^2, 3))."""
    u = np.linspace(-size / 2, size / 2, n)
    g = np.stack(np.meshgrid(u, u, indexing="ij"), axis=-1).reshape(-1, 2)
    z = bump * np.cos(np.pi * g[:, 0] / size) * np.cos(np.pi * g[:, 1] / size)
    k = np.arange(n * n).reshape(n, n)
    a, b, c, d = k[:-1, :-1].ravel(), k[1:, :-1].ravel(), k[1:, 1:].ravel(), k[:-1, 1:].ravel()
    return np.column_stack([g, z]), np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])


def _over_cap(seed: int, height: float, noise: float):
    """The default sheet raised to ``height`` [m] over the body sphere's cap (it cuts the sheet),
    with Gaussian noise of ``noise`` [m]: (rest (V, 3), faces, prediction (V, 3) float64 tensor)."""
    rest, faces = _sheet()
    rng = np.random.default_rng(seed)
    return rest, faces, torch.tensor(rest + [0.0, 0.0, height] + rng.normal(scale=noise, size=rest.shape))


_BODY: dict = {}


def _body():
    """(body vertices (B, 3) float64 tensor, CollisionSurface) of a 0.3 m icosphere at the origin."""
    if not _BODY:
        m = trimesh.creation.icosphere(subdivisions=3, radius=0.3)
        _BODY["v"] = torch.tensor(np.asarray(m.vertices))
        _BODY["s"] = CollisionSurface(np.asarray(m.faces), np.asarray(m.vertices))
    return _BODY["v"], _BODY["s"]


def _rotation(seed):
    q, _ = np.linalg.qr(np.random.default_rng(seed).normal(size=(3, 3)))
    return q * np.sign(np.linalg.det(q))


def _mean_strain2(x, rest):
    """Mean over triangles of ||G||_F^2 (Green strain) of positions x (V, 3) against ClothRest rest."""
    return float((green_strain(torch.as_tensor(x), rest) ** 2).sum((-2, -1)).mean())


def _edges(faces):
    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    return np.unique(np.sort(e, axis=1), axis=0)


def test_rigid_motion_of_the_rest_shape_is_a_fixed_point():
    """A rigidly moved rest shape has zero membrane energy and matches its prediction: it comes back unchanged."""
    rest, faces = _sheet(bump=0.03)
    p = torch.tensor(rest @ _rotation(0).T + FAR + [0.1, -0.2, 0.0])
    bv, surface = _body()
    relax = MetricRelax(rest, faces, dtype=F64)
    out, moved = relax(p, bv, surface, clearance=CLEARANCE)
    assert (out - p).abs().max() < 1e-8 and not moved.any()
    assert abs(float(relax.energy(p, p))) < 1e-20


def test_energy_never_rises_over_the_iterations():
    """Without contacts each local and global step minimises E: E(x_k) is non-increasing in k."""
    rest, faces = _sheet(bump=0.03)
    rng = np.random.default_rng(1)
    p = torch.tensor(rest + FAR + rng.normal(scale=0.01, size=rest.shape))     # half an edge of noise
    bv, surface = _body()
    energies = []
    for k in range(9):   # k = 0: the prediction itself
        x = p if k == 0 else MetricRelax(rest, faces, iterations=k, spectral_radius=0.0, dtype=F64)(p, bv, surface)[0]
        energies.append(float(MetricRelax(rest, faces, dtype=F64).energy(x, p)))
    e = np.array(energies)
    assert np.all(np.diff(e) <= 1e-12 * e[0]), e
    assert e[-1] < 0.2 * e[0]


def test_chebyshev_weights_follow_the_recurrence_to_its_limit():
    """Plain steps (omega = 1) before the delay and for rho = 0; then 2 / (2 - rho^2), falling to the
    Chebyshev limit 2 / (1 + sqrt(1 - rho^2))."""
    assert chebyshev_weights(6, 0.0) == (1.0,) * 6
    rho = 0.9
    w = chebyshev_weights(200, rho, delay=3)
    assert w[:3] == (1.0, 1.0, 1.0) and w[3] == pytest.approx(2.0 / (2.0 - rho ** 2))
    assert np.all(np.diff(w[3:]) <= 0) and w[4] < w[3]
    assert w[-1] == pytest.approx(2.0 / (1.0 + np.sqrt(1.0 - rho ** 2)), rel=1e-12)


def test_chebyshev_reaches_the_plain_fixed_point_in_fewer_iterations():
    """Without contacts: after 16 iterations the accelerated relax has a lower E than plain steps; at
    fidelity 100 (where plain steps converge) 400 accelerated iterations end within 20 um of 2000
    plain ones, and 400 plain ones at least 10x farther."""
    rest, faces = _sheet(bump=0.03)
    rng = np.random.default_rng(11)
    p = torch.tensor(rest @ _rotation(5).T + FAR + rng.normal(scale=0.006, size=rest.shape))
    bv, surface = _body()

    def relaxed(iterations, rho, fidelity=10.0):
        return MetricRelax(rest, faces, iterations=iterations, spectral_radius=rho, fidelity=fidelity,
                           dtype=F64)(p, bv, surface)[0]

    energy = MetricRelax(rest, faces, dtype=F64).energy
    assert float(energy(relaxed(16, 0.95), p)) < 0.9 * float(energy(relaxed(16, 0.0), p))
    converged = relaxed(2000, 0.0, 100.0)
    fast = float((relaxed(400, 0.95, 100.0) - converged).abs().max())
    plain = float((relaxed(400, 0.0, 100.0) - converged).abs().max())
    assert fast < 2e-5 and plain > 10 * fast, (fast, plain)


def test_global_step_equals_a_sparse_solve_of_independently_assembled_system():
    """One iteration = the solve of A x = b assembled in numpy/scipy per triangle, R by SVD, another 2D frame."""
    rest, faces = _sheet(n=8, bump=0.03)
    rng = np.random.default_rng(2)
    p = rest @ _rotation(3).T + FAR + rng.normal(scale=0.005, size=rest.shape)
    fidelity = 37.0
    bv, surface = _body()
    out, _ = MetricRelax(rest, faces, fidelity=fidelity, iterations=1, dtype=F64)(torch.tensor(p), bv, surface)

    nv = len(rest)
    a_mat = scipy.sparse.lil_matrix((nv, nv))
    b = np.zeros((nv, 3))
    m = np.zeros(nv)
    for tri in faces:
        e = (rest[tri[1:]] - rest[tri[0]]).T                      # (3, 2) rest edges
        q, _ = np.linalg.qr(np.column_stack([e, np.cross(e[:, 0], e[:, 1])]))
        dm = q[:, :2].T @ e                                      # rest edges in a 2D frame of the triangle (QR's)
        area = 0.5 * abs(np.linalg.det(dm))
        d = np.linalg.inv(dm).T @ np.array([[-1.0, 1.0, 0.0], [-1.0, 0.0, 1.0]])   # F^T = d @ X
        u, _, vt = np.linalg.svd((d @ p[tri]).T, full_matrices=False)
        r = u @ vt                                               # closest orthonormal 3x2 to F
        k = area * d.T @ d
        for i in range(3):
            m[tri[i]] += area / 3
            b[tri[i]] += area * (d.T @ r.T)[i]
            for j in range(3):
                a_mat[tri[i], tri[j]] += k[i, j]
    a_mat = (a_mat + scipy.sparse.diags(fidelity * m)).tocsc()
    x = scipy.sparse.linalg.spsolve(a_mat, b + fidelity * m[:, None] * p)
    assert np.abs(out.numpy() - x).max() < 1e-9


def test_noise_is_removed_and_the_metric_restored():
    """Gaussian noise of 1/5 edge on the rest sheet: mean ||G||^2 falls 10x and the vertices near the clean sheet."""
    rest, faces = _sheet(bump=0.03)
    edge = 0.2 / 9
    clean = rest + FAR
    rng = np.random.default_rng(4)
    p = torch.tensor(clean + rng.normal(scale=edge / 5, size=rest.shape))
    bv, surface = _body()
    out, _ = MetricRelax(rest, faces, dtype=F64)(p, bv, surface)
    cloth = ClothRest.from_mesh(rest, faces, "cotton", dtype=F64)
    before, after = _mean_strain2(p, cloth), _mean_strain2(out, cloth)
    assert after < 0.1 * before, (before, after)
    err_before = np.linalg.norm(p.numpy() - clean, axis=1).mean()
    err_after = np.linalg.norm(out.numpy() - clean, axis=1).mean()
    assert err_after < 0.8 * err_before, (err_before, err_after)


def test_fidelity_bounds_a_uniform_stretch_between_rest_and_prediction():
    """A 1.2x stretched sheet returns to rest lengths with a weak tie and stays put with a huge one."""
    rest, faces = _sheet()
    p = torch.tensor(rest * [1.2, 1.2, 1.0] + FAR)
    bv, surface = _body()
    edges = _edges(faces)

    def ratio(x):
        x = np.asarray(x)
        return (np.linalg.norm(x[edges[:, 0]] - x[edges[:, 1]], axis=1)
                / np.linalg.norm(rest[edges[:, 0]] - rest[edges[:, 1]], axis=1)).mean()

    assert abs(ratio(p) - 1.2) < 1e-12
    weak, _ = MetricRelax(rest, faces, fidelity=1.0, dtype=F64)(p, bv, surface)
    assert abs(ratio(weak) - 1.0) < 0.02, ratio(weak)
    strong, _ = MetricRelax(rest, faces, fidelity=1e8, dtype=F64)(p, bv, surface)
    assert (strong - p).abs().max() < 1e-5 and abs(ratio(strong) - 1.2) < 1e-4


def test_contacts_leave_every_vertex_outside_and_flag_the_moved_ones():
    """A sheet cut by a sphere's cap: all vertices end >= clearance outside; moved = start contacts | final push."""
    rest, faces, p = _over_cap(5, 0.285, 0.003)
    bv, surface = _body()
    relax = MetricRelax(rest, faces, dtype=F64)
    out, moved = relax(p, bv, surface, clearance=CLEARANCE)
    assert surface.query(out, bv).distance.min() >= CLEARANCE - 1e-6
    d0 = surface.query(p, bv).distance[0]
    assert (d0 < 0).sum() > 10
    before_push, touching = relax._relax(p[None], bv[None], surface, CLEARANCE)
    final = push_out(before_push, bv[None], surface, clearance=CLEARANCE)[0][0]
    pushed = (final - before_push[0]).norm(dim=-1) > PUSH_TOLERANCE
    assert torch.equal(touching[0], d0 < CLEARANCE)
    assert torch.equal(moved, (d0 < CLEARANCE) | pushed)
    assert torch.equal(out, final)
    # The metric is restored where the plain push-out leaves the noise and stretches the cap's rim.
    cloth = ClothRest.from_mesh(rest, faces, "cotton", dtype=F64)
    plain, _ = push_out(p, bv, surface, clearance=CLEARANCE)
    assert _mean_strain2(out, cloth) < 0.1 * _mean_strain2(plain, cloth)


def test_contact_planes_alone_hold_a_convex_body_off():
    """On a convex body each tangent half-space lies outside it: with every vertex in the contact band,
    the iterations alone end >= clearance outside, and the final push moves nothing."""
    rest, faces, p = _over_cap(5, 0.285, 0.003)
    bv, surface = _body()
    relax = MetricRelax(rest, faces, contact_band=0.1, dtype=F64)
    before_push, touching = relax._relax(p[None], bv[None], surface, CLEARANCE)
    assert surface.query(before_push, bv[None]).distance.min() >= CLEARANCE - 1e-9
    out, moved = relax(p, bv, surface, clearance=CLEARANCE)
    assert (out - before_push[0]).abs().max() < 1e-12       # (a push by rounding still counts as moved)
    assert int(touching.sum()) > 10 and bool(moved[touching[0]].all())


def test_renewed_planes_hold_the_sliding_cloth_off_before_the_final_push():
    """The noisy sheet over the cap slides as its metric returns: vertices outside the 1-cm band at
    the start reach the sphere later. With the planes renewed every CONTACT_REFRESH iterations none
    is inside the clearance before the final push (with the start's planes only, 10 end 2.4 cm in)."""
    rest, faces, p = _over_cap(5, 0.285, 0.003)
    bv, surface = _body()
    relax = MetricRelax(rest, faces, iterations=64, dtype=F64)
    assert int((surface.query(p, bv).distance < CLEARANCE + relax.contact_band).sum()) < len(rest)
    before_push, _ = relax._relax(p[None], bv[None], surface, CLEARANCE)
    assert surface.query(before_push, bv[None]).distance.min() >= CLEARANCE - 1e-9


def test_with_contacts_the_default_acceleration_ends_where_plain_steps_do():
    """The sheet over the cap, 128 iterations: rho 0.95 (the default) reaches the energy of plain steps."""
    rest, faces, p = _over_cap(5, 0.285, 0.003)
    bv, surface = _body()
    energy = MetricRelax(rest, faces, dtype=F64).energy
    ends = [float(energy(MetricRelax(rest, faces, iterations=128, spectral_radius=rho, dtype=F64)._relax(
        p[None], bv[None], surface, CLEARANCE)[0][0], p)) for rho in (0.0, 0.95)]
    assert abs(ends[1] - ends[0]) < 1e-4 * ends[0], ends


def test_collapsed_triangles_give_finite_output():
    """Triangles whose three vertices coincide (F = 0) and a collinear one give finite R, output and energy."""
    rest, faces = _sheet()
    p = rest + FAR
    p[faces[40]] = p[faces[40][0]]                  # collapse one triangle to a point
    p[faces[100][1]] = 0.5 * (p[faces[100][0]] + p[faces[100][2]])   # and another onto a line
    p = torch.tensor(p)
    bv, surface = _body()
    for dtype in (F64, torch.float32):
        relax = MetricRelax(rest, faces, dtype=dtype)
        out, _ = relax(p.to(dtype), bv.to(dtype), surface)
        assert out.dtype == dtype and torch.isfinite(out).all()
        assert torch.isfinite(relax.energy(out, p.to(dtype))).all()


def test_bad_input_raises_input_error_naming_the_argument():
    """Wrong shapes, fidelity <= 0, iterations < 1 and bad faces are refused with the argument named."""
    rest, faces = _sheet(n=4)
    bv, surface = _body()
    with pytest.raises(InputError, match="fidelity"):
        MetricRelax(rest, faces, fidelity=0.0)
    with pytest.raises(InputError, match="iterations"):
        MetricRelax(rest, faces, iterations=0)
    for rho in (1.0, -0.1, float("nan")):
        with pytest.raises(InputError, match="spectral_radius"):
            MetricRelax(rest, faces, spectral_radius=rho)
    with pytest.raises(InputError, match="rest_positions"):
        MetricRelax(rest[:, :2], faces)
    with pytest.raises(InputError, match="faces"):
        MetricRelax(rest, faces + 1)
    relax = MetricRelax(rest, faces, dtype=F64)
    p = torch.tensor(rest)
    with pytest.raises(InputError, match=r"points must have shape .*got \(15, 3\)"):
        relax(p[:-1], bv, surface)
    with pytest.raises(InputError, match="body_vertices"):
        relax(p[None].expand(2, -1, -1), bv[:-1], surface)
    with pytest.raises(InputError, match="target"):
        relax.energy(p, p[None].expand(2, -1, -1))


def test_single_frame_equals_a_batch_of_one():
    """(V, 3) input gives exactly the (1, V, 3) result, and frames of a batch are relaxed independently."""
    rest, faces, p = _over_cap(6, 0.29, 0.004)
    rng = np.random.default_rng(16)     # another frame's noise
    q = torch.tensor(rest + FAR + rng.normal(scale=0.004, size=rest.shape))
    bv, surface = _body()
    relax = MetricRelax(rest, faces, dtype=F64)
    single, moved1 = relax(p, bv, surface)
    batch, moved = relax(torch.stack([p, q]), torch.stack([bv, bv]), surface)
    assert single.shape == p.shape and moved1.shape == (len(rest),) and moved1.any()
    assert (single - batch[0]).abs().max() < 1e-12 and torch.equal(moved1, moved[0])
    assert (relax(q, bv, surface)[0] - batch[1]).abs().max() < 1e-12


def test_the_gpu_factor_solves_like_the_cpu_factor():
    """The dense inverse a GPU gets (here built on the CPU) relaxes exactly as the CPU's sparse LU."""
    from simgen.learn.relax import _dense_inverse

    rest, faces, p = _over_cap(7, 0.29, 0.004)
    bv, surface = _body()
    relax = MetricRelax(rest, faces, dtype=F64)
    by_lu, moved_lu = relax(p, bv, surface)
    relax._lu, relax.ainv = None, _dense_inverse(relax.matrix, torch.device("cpu"))
    by_inverse, moved_inverse = relax(p, bv, surface)
    assert (by_lu - by_inverse).abs().max() < 1e-9 and torch.equal(moved_lu, moved_inverse)


def test_a_float32_gpu_factor_stays_precise_far_from_the_origin():
    """2 m from the origin, the float32 dense inverse (a GPU's factor, built here on the CPU) relaxes
    as the float64 solve does to 10 um: the global step solves for the offsets from the centroid.
    The body stays at the origin: where contacts are renewed, a vertex at the band's edge may get a
    plane in one precision and not in the other (a discrete difference, not the solve's)."""
    from simgen.learn.relax import _dense_inverse

    rest, faces = _sheet(n=50, size=1.0)            # 2,500 vertices, 2 cm edges, like a garment's
    rng = np.random.default_rng(8)
    offset = np.array([1.5, 1.2, 0.6])
    p = rest + offset + rng.normal(scale=0.004, size=rest.shape)
    bv, surface = _body()
    exact, _ = MetricRelax(rest, faces, dtype=F64)(torch.tensor(p), bv, surface)
    relax = MetricRelax(rest, faces, dtype=torch.float32)
    relax._lu, relax.ainv = None, _dense_inverse(relax.matrix, torch.device("cpu")).float()
    single, _ = relax(torch.tensor(p, dtype=torch.float32), bv.float(), surface)
    assert (single.double() - exact).abs().max() < 1e-5
    # With the sphere moved with the sheet (it cuts through it) float32 still leaves every vertex out.
    near = bv.float() + torch.tensor(offset, dtype=torch.float32)
    held, moved = relax(torch.tensor(p, dtype=torch.float32), near, surface)
    assert surface.query(held, near).distance.min() >= CLEARANCE - 1e-5 and int(moved.sum()) > 100


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_one_frame_replayed_from_cuda_graphs_equals_the_eager_iterations():
    """On a GPU one frame's iterations replay CUDA graphs (one per stretch between body queries); two
    frames run eagerly: the first of two equal frames matches the graphed frame, also on a second call."""
    rest, faces, p = _over_cap(6, 0.285, 0.004)
    bv, surface = _body()
    dev = torch.device("cuda")
    # float64: in float32 the two paths' rounding differs by ~1e-7 m, enough to flip a vertex that
    # sits on a contact band's edge in or out of its contact set (3e-5 m apart then, on an H200).
    relax = MetricRelax(rest, faces, device=dev, dtype=F64)
    one = p.double().to(dev)
    body = bv.double().to(dev)
    graphed, moved = relax(one, body, surface)
    eager, moved2 = relax(torch.stack([one, one]), torch.stack([body, body]), surface)
    assert len(relax._graphs.graphs) == 2
    assert (graphed - eager[0]).abs().max() < 1e-9 and torch.equal(moved, moved2[0])
    again, _ = relax(one + 0.001, body, surface)
    shifted, _ = relax(torch.stack([one + 0.001] * 2), torch.stack([body, body]), surface)
    assert (again - shifted[0]).abs().max() < 1e-9 and len(relax._graphs.graphs) == 2
    # float32, the GPU's default: the same to the rounding and those flips (a stale graph input
    # would be 1 mm off).
    relax32 = MetricRelax(rest, faces, device=dev)
    for shift in (0.0, 0.001):
        one32, body32 = (p + shift).float().to(dev), bv.float().to(dev)
        graphed32, _ = relax32(one32, body32, surface)
        eager32, _ = relax32(torch.stack([one32, one32]), torch.stack([body32, body32]), surface)
        assert (graphed32 - eager32[0]).abs().max() < 1e-4
