"""Energies of the Warp cloth solver: finite differences, analytic values, invariances, PSD.

The float64 kernels (the same code as the float32 solver kernels, built for wp.float64) are checked
against central finite differences of themselves: the gradient against the energy, the Hessian
against the gradient wherever the assembled Hessian is the exact one (membrane unprojected or in
stretch, bending at its rest angle, contact with the closest point inside a body face, friction,
inertia, damping at equal angles). They are also checked against the independent numpy references
of :mod:`simgen.sim.energies.reference`, and the float32 kernels against those references.
"""

import math
from dataclasses import replace

import numpy as np
import pytest
import trimesh
import warp as wp
from scipy.spatial.transform import Rotation

from simgen.errors import InputError
from simgen.sim import ClothModel, ClothModelBuilder, get_material
from simgen.sim.energies import (
    ContactFrame,
    ContactParams,
    FrictionParams,
    GravityParams,
    eval_attachment,
    eval_bending,
    eval_contact,
    eval_damping,
    eval_floor,
    eval_friction,
    eval_gravity,
    eval_inertia,
    eval_membrane,
    load_kernels,
    update_contact_frame,
)
from simgen.sim.energies import reference as ref

wp.config.quiet = True

FD_STEP = 1e-6  # [m], central differences in float64 on ~0.1 m meshes
FD_TOL = 1e-6   # relative error bound of the float64 checks (observed ~1e-9 .. 1e-8)


# -- helpers ----------------------------------------------------------------------------------------

def grid(n=3, size=0.1):
    """A flat n x n vertex grid in the xz plane (Y-up), two triangles per cell, normals +y."""
    xs = np.linspace(0.0, size, n)
    X, Z = np.meshgrid(xs, xs, indexing="ij")
    v = np.stack([X.ravel(), np.zeros(n * n), Z.ravel()], axis=1)
    f = []
    for i in range(n - 1):
        for j in range(n - 1):
            a, b, c, d = i * n + j, (i + 1) * n + j, (i + 1) * n + j + 1, i * n + j + 1
            f += [[a, d, c], [a, c, b]]
    return v, np.array(f)


def curved_template(seed=0, n=3):
    """A slightly crumpled grid: non-flat rest angles, generic triangles."""
    v, f = grid(n)
    rng = np.random.default_rng(seed)
    return v + 0.006 * rng.normal(size=v.shape), f


def model64(vertices, faces, material="snug_cotton", **kw):
    return ClothModel.from_mesh(vertices, faces, material, device="cpu", dtype=wp.float64, **kw)


def vec3_array(model, x):
    return wp.array(np.asarray(x, dtype=np.float64), dtype=model.vec3, device=model.device)


def dense(model, hessian) -> np.ndarray:
    """The BSR Hessian as a dense (3V, 3V) float64 matrix."""
    vals = hessian.values.numpy().astype(np.float64)
    rows, cols = model.pattern.rows, model.pattern.columns
    out = np.zeros((3 * model.num_vertices, 3 * model.num_vertices))
    for s in range(len(vals)):
        out[3 * rows[s]:3 * rows[s] + 3, 3 * cols[s]:3 * cols[s] + 3] += vals[s]
    return out


def evaluate(model, term, x, *args, **kw):
    """(per-instance energies, gradient (V, 3), dense Hessian) of one term at positions x."""
    e, g, h = model.new_energy(), model.new_gradient(), model.new_hessian()
    term(model, vec3_array(model, x), *args, energy=e, gradient=g, hessian=h, **kw)
    return e.numpy().astype(np.float64), g.numpy().astype(np.float64), dense(model, h)


def energy_of(model, term, *args, **kw):
    def f(x):
        e = model.new_energy()
        term(model, vec3_array(model, x), *args, energy=e, **kw)
        return float(e.numpy().sum())
    return f


def gradient_of(model, term, *args, **kw):
    def g(x):
        out = model.new_gradient()
        term(model, vec3_array(model, x), *args, gradient=out, **kw)
        return out.numpy().astype(np.float64)
    return g


def fd_gradient(f, x, h=FD_STEP):
    out = np.zeros_like(x)
    for i in range(x.shape[0]):
        for j in range(3):
            xp, xm = x.copy(), x.copy()
            xp[i, j] += h
            xm[i, j] -= h
            out[i, j] = (f(xp) - f(xm)) / (2 * h)
    return out


def fd_hessian(g, x, h=FD_STEP):
    n = x.size
    out = np.zeros((n, n))
    for k in range(n):
        xp, xm = x.copy(), x.copy()
        xp.reshape(-1)[k] += h
        xm.reshape(-1)[k] -= h
        out[:, k] = (g(xp) - g(xm)).reshape(-1) / (2 * h)
    return out


def rel_err(a, b):
    return float(np.max(np.abs(a - b)) / max(np.max(np.abs(b)), 1e-300))


def check_fd(model, term, x, *args, hessian=True, step=FD_STEP, **kw):
    """Assert gradient (and Hessian) match finite differences; returns the two relative errors."""
    _, g, hmat = evaluate(model, term, x, *args, **kw)
    eg = rel_err(g, fd_gradient(energy_of(model, term, *args, **kw), x, step))
    assert eg < FD_TOL, f"gradient FD relative error {eg:.2e}"
    eh = None
    if hessian:
        eh = rel_err(hmat, fd_hessian(gradient_of(model, term, *args, **kw), x, step))
        assert eh < FD_TOL, f"Hessian FD relative error {eh:.2e}"
    return eg, eh


def min_eig_rel(hmat):
    w = np.linalg.eigvalsh(0.5 * (hmat + hmat.T))
    return w.min() / max(abs(w).max(), 1e-300)


def rigid(x, seed=3):
    r = Rotation.random(random_state=seed).as_matrix()
    return x @ r.T + np.array([0.3, -0.2, 0.5])


# -- membrane ---------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def crumpled():
    rest, faces = curved_template()
    return rest, faces, model64(rest, faces)


def stretched(rest, seed=1):
    rng = np.random.default_rng(seed)
    return rest @ np.diag([1.08, 1.05, 1.06]) + 0.001 * rng.normal(size=rest.shape)


def compressed(rest, seed=2):
    rng = np.random.default_rng(seed)
    return rest @ np.diag([0.85, 1.0, 0.9]) + 0.004 * rng.normal(size=rest.shape)


def test_membrane_fd_exact_hessian_in_stretch_and_compression(crumpled):
    rest, faces, m = crumpled
    for x in (stretched(rest), compressed(rest)):
        check_fd(m, eval_membrane, x, project=False)


def test_membrane_projection_inactive_in_stretch_psd_in_compression(crumpled):
    rest, faces, m = crumpled
    x = stretched(rest)
    _, _, h_proj = evaluate(m, eval_membrane, x)
    _, _, h_full = evaluate(m, eval_membrane, x, project=False)
    assert rel_err(h_proj, h_full) < 1e-12
    x = compressed(rest)
    _, _, h_proj = evaluate(m, eval_membrane, x)
    _, _, h_full = evaluate(m, eval_membrane, x, project=False)
    assert min_eig_rel(h_full) < -1e-3  # compression makes the exact Hessian indefinite ...
    assert min_eig_rel(h_proj) > -1e-12  # ... and the projection fixes it
    # Jacobi sweeps in the kernel == numpy's eigh in the reference, also with inverted triangles
    h_ref = ref.membrane_hessian(x, rest, faces, m.host.tri_lambda, m.host.tri_mu, project=True)
    assert rel_err(h_proj, h_ref) < 1e-10
    x = rest + 0.03 * np.random.default_rng(14).normal(size=rest.shape)
    _, _, h_proj = evaluate(m, eval_membrane, x)
    h_ref = ref.membrane_hessian(x, rest, faces, m.host.tri_lambda, m.host.tri_mu, project=True)
    assert rel_err(h_proj, h_ref) < 1e-10 and min_eig_rel(h_proj) > -1e-12


def test_membrane_matches_frame_free_reference(crumpled):
    rest, faces, m = crumpled
    for x in (stretched(rest), compressed(rest)):
        e, g, _ = evaluate(m, eval_membrane, x)
        e_ref, g_ref = ref.membrane(x, rest, faces, m.host.tri_lambda, m.host.tri_mu)
        assert e.sum() == pytest.approx(e_ref.sum(), rel=1e-12)
        assert rel_err(g, g_ref) < 1e-10


def test_membrane_zero_at_rest_and_rigid_invariant(crumpled):
    rest, faces, m = crumpled
    e, g, _ = evaluate(m, eval_membrane, rest)
    assert abs(e.sum()) < 1e-20 and np.abs(g).max() < 1e-12
    e, g, _ = evaluate(m, eval_membrane, rigid(rest))
    assert abs(e.sum()) < 1e-18 and np.abs(g).max() < 1e-10
    x = stretched(rest)
    assert evaluate(m, eval_membrane, rigid(x))[0].sum() == pytest.approx(evaluate(m, eval_membrane, x)[0].sum(),
                                                                          rel=1e-10)


def test_membrane_uniaxial_stretch_by_hand():
    # Right triangle with legs 0.1 m, stretched by s along x (the first edge): F = diag(s, 1),
    # G = diag((s^2 - 1)/2, 0), Psi = lambda/2 g^2 + mu g^2, E = A h Psi.
    rest = np.array([[0.0, 0.0, 0.0], [0.1, 0.0, 0.0], [0.0, 0.1, 0.0]])
    m = model64(rest, [[0, 1, 2]])
    cotton = get_material("snug_cotton")
    s = 1.1
    x = rest * np.array([s, 1.0, 1.0])
    g = 0.5 * (s * s - 1.0)
    expected = 0.5 * 0.1 * 0.1 * cotton.thickness * (0.5 * cotton.lame_lambda * g * g + cotton.lame_mu * g * g)
    assert evaluate(m, eval_membrane, x)[0].sum() == pytest.approx(expected, rel=1e-12)


def test_membrane_scale_and_float32_against_reference(crumpled):
    rest, faces, m = crumpled
    x = compressed(rest)
    e1, g1, h1 = evaluate(m, eval_membrane, x)
    e2, g2, h2 = evaluate(m, eval_membrane, x, scale=2.5)
    assert np.allclose(e2, 2.5 * e1, rtol=1e-13) and np.allclose(g2, 2.5 * g1, rtol=1e-13)
    assert np.allclose(h2, 2.5 * h1, rtol=1e-12, atol=1e-12 * np.abs(h1).max())
    m32 = ClothModel.from_mesh(rest, faces, "snug_cotton", device="cpu")
    e, g, h = evaluate(m32, eval_membrane, x)
    e_ref, g_ref = ref.membrane(x, rest, faces, m.host.tri_lambda, m.host.tri_mu)
    assert e.sum() == pytest.approx(e_ref.sum(), rel=1e-4)
    assert rel_err(g, g_ref) < 1e-4
    h_ref = ref.membrane_hessian(x, rest, faces, m.host.tri_lambda, m.host.tri_mu, project=True)
    assert rel_err(h, h_ref) < 1e-4
    assert min_eig_rel(h) > -1e-5


# -- bending ----------------------------------------------------------------------------------------

def test_bending_gradient_fd_and_gauss_newton_exact_at_rest(crumpled):
    rest, faces, m = crumpled
    check_fd(m, eval_bending, compressed(rest), hessian=False)
    # At the rest angle the dropped term k (theta - theta_rest) d2theta vanishes: GN == exact.
    x = rigid(rest)
    e, g, h = evaluate(m, eval_bending, x)
    assert abs(e.sum()) < 1e-20 and np.abs(g).max() < 1e-12
    assert rel_err(h, fd_hessian(gradient_of(m, eval_bending), x)) < FD_TOL
    assert min_eig_rel(evaluate(m, eval_bending, compressed(rest))[2]) > -1e-12


def test_bending_matches_reference_and_is_rigid_invariant(crumpled):
    rest, faces, m = crumpled
    x = compressed(rest)
    e, g, h = evaluate(m, eval_bending, x)
    e_ref, g_ref = ref.bending(x, m.host.hinges, m.host.hinge_stiffness, m.host.hinge_rest_angle)
    assert e.sum() == pytest.approx(e_ref.sum(), rel=1e-12) and rel_err(g, g_ref) < 1e-10
    assert rel_err(h, ref.bending_hessian_gn(x, m.host.hinges, m.host.hinge_stiffness)) < 1e-12
    assert evaluate(m, eval_bending, rigid(x))[0].sum() == pytest.approx(e.sum(), rel=1e-10)
    m32 = ClothModel.from_mesh(rest, faces, "snug_cotton", device="cpu")
    e32, g32, _ = evaluate(m32, eval_bending, x)
    assert e32.sum() == pytest.approx(e_ref.sum(), rel=1e-4) and rel_err(g32, g_ref) < 1e-4


@pytest.mark.parametrize("phi", [0.3, -0.7, 2.0])
def test_bending_hinge_folded_by_known_angle(phi):
    # Two triangles on the edge x0-x1 (the z axis); the wing x3 rotates by phi about the edge.
    rest = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 0.1], [0.08, 0.0, 0.05], [-0.06, 0.0, 0.04]])
    faces = np.array([[0, 1, 2], [1, 0, 3]])
    k_bend = 3.96e-5
    a1, a2 = 0.5 * 0.1 * 0.08, 0.5 * 0.1 * 0.06
    k_scale = 0.1**2 / (4.0 * (a1 + a2))
    c, s = np.cos(phi), np.sin(phi)
    x = rest.copy()
    x[3] = [-0.06 * c, -0.06 * s, 0.04]
    for mode in ("flat", "template"):  # the template is flat: both give theta_rest = 0
        m = model64(rest, faces, "snug_cotton", bending_rest=mode)
        assert m.num_hinges == 1 and m.host.hinge_stiffness[0] == pytest.approx(k_bend * k_scale, rel=1e-12)
        e, _, _ = evaluate(m, eval_bending, x)
        assert e.sum() == pytest.approx(k_bend * k_scale * phi**2 / 2, rel=1e-10)
        assert abs(ref.dihedral_angles(x, m.host.hinges)[0]) == pytest.approx(abs(phi), rel=1e-12)


def test_bending_template_rest_angle_vs_flat(crumpled):
    rest, faces, m = crumpled
    assert np.abs(m.host.hinge_rest_angle).max() > 0.05  # the template is really curved
    e, _, _ = evaluate(m, eval_bending, rest)
    assert abs(e.sum()) < 1e-20
    flat = model64(rest, faces, bending_rest="flat")
    e_flat, _, _ = evaluate(flat, eval_bending, rest)
    expected = 0.5 * np.sum(flat.host.hinge_stiffness * ref.dihedral_angles(rest, flat.host.hinges) ** 2)
    assert e_flat.sum() == pytest.approx(expected, rel=1e-12) and expected > 0


# -- gravity, inertia -------------------------------------------------------------------------------

def test_gravity_is_m_g_h(crumpled):
    rest, faces, m = crumpled
    x = rigid(rest)
    e, g, h = evaluate(m, eval_gravity, x)
    assert e.sum() == pytest.approx(np.sum(m.host.vertex_mass * 9.81 * x[:, 1]), rel=1e-12)
    assert np.abs(h).max() == 0.0
    check_fd(m, eval_gravity, x, hessian=False)
    e2, g2, _ = evaluate(m, eval_gravity, x, GravityParams((1.0, 2.0, 3.0)))
    assert rel_err(g2, ref.gravity(x, m.host.vertex_mass, (1.0, 2.0, 3.0))[1]) < 1e-14


def test_inertia_fd_and_mass_over_h2(crumpled):
    rest, faces, m = crumpled
    rng = np.random.default_rng(4)
    x_hat = vec3_array(m, rest + 0.01 * rng.normal(size=rest.shape))
    dt = 1.0 / 300.0
    x = rest + 0.01 * rng.normal(size=rest.shape)
    check_fd(m, eval_inertia, x, x_hat, dt)
    e, g, h = evaluate(m, eval_inertia, x, x_hat, dt)
    assert np.allclose(np.diag(h), np.repeat(m.host.vertex_mass / dt**2, 3), rtol=1e-14)
    e_ref, g_ref = ref.inertia(x, x_hat.numpy(), m.host.vertex_mass, dt)
    assert e.sum() == pytest.approx(e_ref.sum(), rel=1e-12) and rel_err(g, g_ref) < 1e-12
    with pytest.raises(InputError):
        eval_inertia(m, vec3_array(m, x), x_hat, 0.0, energy=m.new_energy())


# -- batches: per-instance sums ---------------------------------------------------------------------

def _cuda_available() -> bool:
    try:
        return wp.is_cuda_available()
    except Exception:  # noqa: BLE001 - no driver at all
        return False


@pytest.mark.parametrize("device", ["cpu", pytest.param("cuda:0", marks=[
    pytest.mark.gpu, pytest.mark.skipif(not _cuda_available(), reason="needs CUDA")])])
def test_batch_energies_are_each_instances_own(device):
    # Instances of 15x15, 9x9 and 23x23 grids (with damping, so every dense term runs), concatenated:
    # on CUDA their boundaries fall inside blocks of 256 threads, where the block reduction must give
    # each instance exactly its own energy.
    material = replace(get_material("snug_cotton"), damping_stiffness=2.0e-3, damping_mass=0.5)
    rng = np.random.default_rng(7)
    singles, xs = [], []
    for n in (15, 9, 23):
        v, f = grid(n, 0.3)
        v = v + 0.004 * rng.normal(size=v.shape)
        singles.append(ClothModel.from_mesh(v, f, material, device=device))
        xs.append(v + 0.01 * rng.normal(size=v.shape))
    batch = ClothModel.concatenate(singles)
    dt = 1.0 / 300.0
    x_all = np.concatenate(xs)

    def energies(model, x, x_other, term):
        e = model.new_energy()
        xw = wp.array(x.astype(np.float32), dtype=model.vec3, device=device)
        ow = wp.array(x_other.astype(np.float32), dtype=model.vec3, device=device)
        if term in (eval_inertia, eval_damping):
            term(model, xw, ow, dt, energy=e)
        else:
            term(model, xw, energy=e)
        return e.numpy().astype(np.float64)

    for term in (eval_membrane, eval_bending, eval_gravity, eval_inertia, eval_damping):
        own = [energies(m, x, m.host.rest_positions, term)[0] for m, x in zip(singles, xs)]
        together = energies(batch, x_all, np.concatenate([m.host.rest_positions for m in singles]), term)
        assert np.all(np.abs(np.array(own)) > 0), term.__name__
        assert together == pytest.approx(own, rel=1e-4), term.__name__


# -- body contact -----------------------------------------------------------------------------------

def box_body(center=(0.0, 0.0, 0.0), half=0.125):
    box = trimesh.creation.box(extents=(2 * half,) * 3)
    v = np.asarray(box.vertices) + np.asarray(center)
    mesh = wp.Mesh(points=wp.array(v, dtype=wp.vec3, device="cpu"),
                   indices=wp.array(np.asarray(box.faces, dtype=np.int32).reshape(-1), dtype=wp.int32, device="cpu"))
    return mesh, v.astype(np.float32).astype(np.float64), np.asarray(box.faces)


@pytest.fixture(scope="module")
def box():
    return box_body()


def mesh_ids(*meshes):
    return wp.array([0 if m is None else m.id for m in meshes], dtype=wp.uint64, device="cpu")


def cloth_over_top_face(depths, half=0.125):
    """A small cloth grid above the box's top face (y = half) whose vertices sit at the given
    signed distances (interior closest points). The grid is kept off the face's diagonal: there two
    body triangles are equally close and the float32 query may pick either, whose distances agree
    only to second order in the offset (invisible to the solver, not to float64 differences)."""
    v, f = grid(3, size=0.1)
    v = v - np.array([0.037, 0.0, 0.071])
    v[:, 1] = half + np.asarray(depths)
    return v, f


def test_contact_analytic_fd_and_reference(box):
    mesh, bv, bf = box
    params = ContactParams(margin=2e-3, stiffness=1e4, power=3)
    depths = np.array([1.5e-3, 0.5e-3, -1.0e-3, 3e-3, 1.0e-3, -2.5e-3, 0.2e-3, 5e-3, 1.8e-3])
    x, f = cloth_over_top_face(depths)
    m = model64(x, f)
    ids = mesh_ids(mesh)
    e, g, h = evaluate(m, eval_contact, x, ids, params)
    pen = np.maximum(params.margin - depths, 0.0)
    assert e.sum() == pytest.approx(np.sum(params.stiffness * pen**3), rel=1e-9)
    # interior closest points: d is linear, so the PSD Hessian is the exact one
    check_fd(m, eval_contact, x, ids, params)
    e_ref, g_ref = ref.contact(x, bv, bf, params.margin, params.stiffness, params.power)
    assert e.sum() == pytest.approx(e_ref.sum(), rel=1e-9) and rel_err(g, g_ref) < 1e-9
    assert min_eig_rel(h) > -1e-12
    # SNUG's values, and power 2 (Hessian constant in d)
    for p in (ContactParams.snug(), ContactParams(power=2.0, stiffness=50.0)):
        e, _, _ = evaluate(m, eval_contact, x, ids, p)
        assert e.sum() == pytest.approx(np.sum(p.stiffness * np.maximum(p.margin - depths, 0) ** p.power), rel=1e-9)
        check_fd(m, eval_contact, x, ids, p)


def test_contact_near_edges_and_corners_gradient(box):
    mesh, bv, bf = box
    params = ContactParams()
    rng = np.random.default_rng(5)
    # points outside the box near its top edges and a corner (point-distance branch), one inside
    # near an edge and two over face interiors
    x = np.array([[0.126, 0.1258, 0.0], [0.1258, 0.1259, 0.1257], [0.0, 0.1255, -0.1262],
                  [0.1248, 0.1243, 0.03], [0.05, 0.1262, 0.1249], [-0.126, 0.1, 0.05]])
    x = x + 1e-5 * rng.normal(size=x.shape)
    faces = np.array([[0, 1, 2], [3, 4, 5]])
    m = model64(x, faces)
    ids = mesh_ids(mesh)
    e, g, h = evaluate(m, eval_contact, x, ids, params)
    e_ref, g_ref = ref.contact(x, bv, bf, params.margin, params.stiffness, params.power)
    assert e.sum() > 0 and e.sum() == pytest.approx(e_ref.sum(), rel=1e-6)
    assert rel_err(g, g_ref) < 1e-6
    check_fd(m, eval_contact, x, ids, params, hessian=False)
    assert min_eig_rel(h) > -1e-12


def test_contact_bodies_per_instance(box):
    mesh_a, _, _ = box
    mesh_b, _, _ = box_body(center=(1.0, 0.0, 0.0))
    x, f = cloth_over_top_face(np.full(9, 1e-3))
    builder = ClothModelBuilder()
    builder.add_instance(x, f, "snug_cotton")                         # over body A
    builder.add_instance(x + [1.0, 0.0, 0.0], f, "snug_cotton")       # over body B
    builder.add_instance(x, f, "snug_cotton")                         # no body
    m = builder.finalize("cpu", dtype=wp.float64)
    xx = m.host.rest_positions
    params = ContactParams()
    one = params.stiffness * (params.margin - 1e-3) ** 3 * 9
    e, g, _ = evaluate(m, eval_contact, xx, mesh_ids(mesh_a, mesh_b, None), params)
    assert e == pytest.approx([one, one, 0.0], rel=1e-9)
    assert np.abs(g[18:]).max() == 0.0
    # one shared mesh would be wrong: instance B's cloth is far from body A
    e, _, _ = evaluate(m, eval_contact, xx, mesh_ids(mesh_a, mesh_a, mesh_a), params)
    assert e == pytest.approx([one, 0.0, one], rel=1e-9)


def test_contact_params_validation():
    assert ContactParams.snug().stiffness == 250.0
    for bad in (dict(margin=0.0), dict(stiffness=-1.0), dict(power=1.5), dict(query_distance=1e-3)):
        with pytest.raises(InputError):
            ContactParams(**bad)


# -- floor and attachment ---------------------------------------------------------------------------

def test_floor_analytic_and_fd():
    """E = k max(margin - (y - h), 0)^p per vertex, heights on both sides of the margin and below
    the floor; gradient and Hessian against float64 finite differences, for p = 3 and p = 2."""
    v, f = grid(3, size=0.1)
    heights = np.array([1.5e-3, 0.5e-3, -1.0e-3, 3e-3, 1.0e-3, -2.5e-3, 0.2e-3, 5e-3, 1.8e-3])
    floor = 0.25
    v[:, 1] = floor + heights
    m = model64(v, f)
    for p in (ContactParams(margin=2e-3, stiffness=1e4, power=3), ContactParams(power=2.0, stiffness=50.0)):
        e, _, h = evaluate(m, eval_floor, v, floor, p)
        assert e.sum() == pytest.approx(np.sum(p.stiffness * np.maximum(p.margin - heights, 0) ** p.power), rel=1e-9)
        check_fd(m, eval_floor, v, floor, p)
        assert min_eig_rel(h) > -1e-12


def test_attachment_analytic_and_fd(box):
    """k/2 |x - a|^2 with a = the barycentric point of a body triangle plus an offset in its frame
    (t1 along the first edge, n the normal, t2 = n x t1): energy by hand, gradient and Hessian by
    finite differences; an instance without a body mesh has no springs."""
    from simgen.garment.waistband import Attachment

    mesh, bv, bf = box
    x, f = cloth_over_top_face(np.full(9, 4e-3))
    rng = np.random.default_rng(5)
    x = x + 0.003 * rng.normal(size=x.shape)
    verts, faces_b = np.array([0, 4, 7]), np.array([2, 5, 9])
    bary = rng.dirichlet(np.ones(3), size=3)
    offset = 0.004 * rng.normal(size=(3, 3))
    k = np.array([120.0, 80.0, 200.0])
    m = model64(x, f, attachment=Attachment(verts, faces_b, bary, offset, k))
    corners = bv[bf[faces_b]]
    e1 = corners[:, 1] - corners[:, 0]
    n = np.cross(e1, corners[:, 2] - corners[:, 0])
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    t1 = e1 / np.linalg.norm(e1, axis=1, keepdims=True)
    anchor = (np.einsum("ab,abc->ac", bary, corners) + offset[:, :1] * t1 + offset[:, 1:2] * n
              + offset[:, 2:] * np.cross(n, t1))
    e, _, _ = evaluate(m, eval_attachment, x, mesh_ids(mesh))
    assert e.sum() == pytest.approx(np.sum(0.5 * k * np.sum((x[verts] - anchor) ** 2, axis=1)), rel=1e-6)
    check_fd(m, eval_attachment, x, mesh_ids(mesh))
    e, g, _ = evaluate(m, eval_attachment, x, mesh_ids(None))
    assert e.sum() == 0.0 and not g.any()


# -- friction ---------------------------------------------------------------------------------------

def moving_box(velocity):
    box = trimesh.creation.box(extents=(0.25, 0.25, 0.25))
    v = np.asarray(box.vertices)
    return wp.Mesh(points=wp.array(v, dtype=wp.vec3, device="cpu"),
                   indices=wp.array(np.asarray(box.faces, dtype=np.int32).reshape(-1), dtype=wp.int32, device="cpu"),
                   velocities=wp.array(np.tile(velocity, (len(v), 1)), dtype=wp.vec3, device="cpu"))


@pytest.mark.parametrize("slip,max_load", [("sticking", math.inf), ("sliding", math.inf), ("sliding", 20.0)])
def test_friction_fd_reference_and_psd(slip, max_load):
    v_body = np.array([0.2, 0.0, -0.1])
    mesh = moving_box(v_body)
    ids = mesh_ids(mesh)
    depths = np.array([1.5e-3, 0.5e-3, -1.0e-3, 3e-3, 1.0e-3, 1.2e-3, 0.2e-3, 5e-3, 1.8e-3])
    x_start, f = cloth_over_top_face(depths)
    m = model64(x_start, f)
    contact = ContactParams()
    frame = ContactFrame(m)
    update_contact_frame(m, vec3_array(m, x_start), ids, contact, frame)
    force = frame.force.numpy()
    assert np.count_nonzero(force) == 7  # all but the two vertices beyond the margin
    dt = 1.0 / 300.0
    params = FrictionParams(smoothing_velocity=1e-2, max_normal_load=max_load)
    eps = params.smoothing_velocity * dt
    # The friction load: lambda capped at max_normal_load times the vertex weight m g.
    load = np.minimum(force, max_load * 9.81 * m.host.vertex_mass)
    if math.isfinite(max_load):
        assert 0 < np.count_nonzero(load < force) < 7  # the cap binds on some contacts, not all
    rng = np.random.default_rng(6)
    tangential = rng.normal(size=x_start.shape) * np.array([1.0, 0.0, 1.0])
    tangential /= np.linalg.norm(tangential, axis=1, keepdims=True)
    slip_len = 0.4 * eps if slip == "sticking" else 3.0 * eps
    x = x_start + dt * v_body + slip_len * tangential + 1e-5 * rng.normal(size=x_start.shape)
    args = (vec3_array(m, x_start), ids, frame, dt, params)
    e, g, h = evaluate(m, eval_friction, x, *args)
    e_ref, g_ref = ref.friction(x, x_start, frame.normal.numpy(), load, m.host.vertex_friction,
                                np.tile(dt * v_body, (len(x), 1)), eps)
    assert e.sum() == pytest.approx(e_ref.sum(), rel=1e-6) and rel_err(g, g_ref) < 1e-6
    check_fd(m, eval_friction, x, *args, step=2e-4 * eps)  # the mollifier varies on the scale eps
    assert min_eig_rel(h) > -1e-12
    # sliding: force magnitude mu * lambda per vertex, opposite to the slip
    if slip == "sliding":
        mag = np.linalg.norm(g, axis=1)
        assert np.allclose(mag, 0.3 * load, rtol=1e-3)


def test_friction_zero_force_when_moving_with_body():
    v_body = np.array([0.5, 0.0, 0.0])
    mesh = moving_box(v_body)
    ids = mesh_ids(mesh)
    x_start, f = cloth_over_top_face(np.full(9, 1e-3))
    m = model64(x_start, f)
    frame = ContactFrame(m)
    update_contact_frame(m, vec3_array(m, x_start), ids, ContactParams(), frame)
    dt = 0.01
    e, g, _ = evaluate(m, eval_friction, x_start + dt * v_body, vec3_array(m, x_start), ids, frame, dt)
    params = FrictionParams()
    eps = params.smoothing_velocity * dt
    load = np.minimum(frame.force.numpy(), params.max_normal_load * 9.81 * m.host.vertex_mass)
    # zero slip up to the float32 body velocity (barycentric weights summing to 1 +- 1e-7): the
    # sticking stiffness 2 mu lambda / eps times that residual slip
    assert np.abs(g).max() <= 0.3 * load.max() * (2.0 / eps) * 1e-7 * dt * 0.5
    assert e.sum() == pytest.approx(np.sum(0.3 * load * eps / 3.0), rel=1e-9)


# -- damping ----------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def damped():
    rest, faces = curved_template(seed=7)
    mat = get_material("snug_cotton").with_overrides(damping_stiffness=2e-3, damping_mass=0.5)
    return rest, faces, model64(rest, faces, mat)


def test_damping_fd_and_reference(damped):
    rest, faces, m = damped
    dt = 1.0 / 300.0
    x_start = stretched(rest, seed=8)
    xs = vec3_array(m, x_start)
    x = compressed(rest, seed=9)
    check_fd(m, eval_damping, x, xs, dt, hessian=False, project=False)
    e, g, _ = evaluate(m, eval_damping, x, xs, dt)
    h = m.host
    e_ref, g_ref = ref.damping(x, x_start, dt, rest=rest, faces=faces, lam_h=h.tri_lambda, mu_h=h.tri_mu,
                               beta_tri=h.tri_damping, hinges=h.hinges, hinge_stiffness=h.hinge_stiffness,
                               beta_hinge=h.hinge_damping, mass=h.vertex_mass, alpha=h.vertex_damping_mass)
    assert e.sum() == pytest.approx(e_ref, rel=1e-10) and rel_err(g, g_ref) < 1e-10
    # A uniform scaling keeps every dihedral angle: there the Gauss-Newton bending part is exact and,
    # growing strain (dG PSD), so is the unprojected = projected membrane part.
    x = 1.03 * x_start
    check_fd(m, eval_damping, x, xs, dt)


def test_damping_ignores_rigid_motion_and_is_viscous(damped):
    rest, faces, m = damped
    mat = m.instances[0].material.with_overrides(damping_mass=0.0)
    m0 = model64(rest, faces, mat)
    dt = 1.0 / 300.0
    x_start = stretched(rest, seed=10)
    e, g, _ = evaluate(m0, eval_damping, rigid(x_start, seed=11), vec3_array(m0, x_start), dt)
    assert abs(e.sum()) < 1e-18 and np.abs(g).max() < 1e-10
    # Rayleigh: from an unstressed start (the rest shape moved rigidly), the force is
    # -(beta/h) K (x - x_t) to first order, K the stiffness of membrane + bending there (the
    # bending Hessian is exact at the rest angle).
    x_start = rigid(rest, seed=13)
    rng = np.random.default_rng(12)
    dx = 1e-7 * rng.normal(size=rest.shape)
    _, g, _ = evaluate(m0, eval_damping, x_start + dx, vec3_array(m0, x_start), dt, project=False)
    k = evaluate(m0, eval_membrane, x_start, project=False)[2] + evaluate(m0, eval_bending, x_start)[2]
    assert rel_err(g.reshape(-1), (2e-3 / dt) * k @ dx.reshape(-1)) < 1e-4


# -- float32 (the solver's kernels) -----------------------------------------------------------------

def test_float32_kernels_match_float64():
    """Every term's float32 kernel against its float64 twin on the same scene."""
    mesh = moving_box(np.array([0.2, 0.0, -0.1]))
    ids = mesh_ids(mesh)
    x_start, f = cloth_over_top_face(np.array([1.5e-3, 0.5e-3, -1.0e-3, 3e-3, 1.0e-3, 1.2e-3, 0.2e-3, 5e-3, 1.8e-3]))
    rng = np.random.default_rng(15)
    x = x_start + 2e-4 * rng.normal(size=x_start.shape)
    mat = get_material("snug_cotton").with_overrides(damping_stiffness=2e-3, damping_mass=0.5)
    dt = 1.0 / 300.0
    results = {}
    for dtype in (wp.float32, wp.float64):
        m = ClothModel.from_mesh(x_start, f, mat, device="cpu", dtype=dtype)
        xs = vec3_array(m, x_start)
        frame = ContactFrame(m)
        update_contact_frame(m, xs, ids, ContactParams(), frame)
        calls = {
            "membrane": (eval_membrane, ()), "bending": (eval_bending, ()), "gravity": (eval_gravity, ()),
            "inertia": (eval_inertia, (xs, dt)), "contact": (eval_contact, (ids,)),
            "friction": (eval_friction, (xs, ids, frame, dt, FrictionParams(1e-2))),
            "damping": (eval_damping, (xs, dt)),
        }
        results[dtype] = {k: evaluate(m, fn, x, *args) for k, (fn, args) in calls.items()}
    for term, (e64, g64, h64) in results[wp.float64].items():
        e32, g32, h32 = results[wp.float32][term]
        assert e32.sum() == pytest.approx(e64.sum(), rel=2e-4, abs=1e-12), term
        assert rel_err(g32, g64) < 2e-4, term
        if np.abs(h64).max() > 0:
            assert rel_err(h32, h64) < 2e-4, term


def test_load_kernels_before_graph_capture():
    load_kernels(wp.float64, device="cpu")  # compiles or fetches all seven modules; no error
