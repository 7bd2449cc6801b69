"""simgen.physics terms against analytic values, finite differences, brute force and invariants.

(Equality with the Warp solver's kernels is tests/test_physics_parity.py.)
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from simgen.errors import InputError
from simgen.physics import (BodySurface, ClothRest, ContactParams, GravityParams, bending, body_distance, contact,
                            gravity, incremental_potential, inertia, inertia_sequence, membrane, predict, snug_loss)
from simgen.physics.surface_query import REGION_INTERIOR, closest_point_triangle
from simgen.sim import get_material
from simgen.sim.energies import reference as ref

COTTON = get_material("cotton")


def grid(n=4, size=0.1, seed=None):
    """A flat n x n vertex grid in the xz plane (normals +y), optionally crumpled by ~3 mm."""
    xs = np.linspace(0.0, size, n)
    X, Z = np.meshgrid(xs, xs, indexing="ij")
    v = np.stack([X.ravel(), np.zeros(n * n), Z.ravel()], axis=1)
    f = []
    for i in range(n - 1):
        for j in range(n - 1):
            a, b, c, d = i * n + j, (i + 1) * n + j, (i + 1) * n + j + 1, i * n + j + 1
            f += [[a, d, c], [a, c, b]]
    if seed is not None:
        v = v + 0.003 * np.random.default_rng(seed).normal(size=v.shape)
    return v, np.array(f)


def box(half=0.1, subdivisions=2):
    import trimesh

    m = trimesh.creation.box(extents=(2 * half,) * 3)
    for _ in range(subdivisions):
        m = m.subdivide()
    return np.asarray(m.vertices), np.asarray(m.faces)


def fd_gradient(f, x, h=1e-6):
    g = torch.zeros_like(x)
    flat = x.reshape(-1)
    for i in range(flat.numel()):
        xp, xm = flat.clone(), flat.clone()
        xp[i] += h
        xm[i] -= h
        g.view(-1)[i] = (f(xp.view_as(x)) - f(xm.view_as(x))) / (2 * h)
    return g


def autograd(f, x):
    x = x.clone().requires_grad_(True)
    (g,) = torch.autograd.grad(f(x), x)
    return g


# -- rest data -------------------------------------------------------------------------------------

def test_rest_masses_sum_to_area_density_times_area():
    v, f = grid(5, seed=1)
    rest = ClothRest.from_mesh(v, f, COTTON, dtype=torch.float64)
    area = 0.5 * np.linalg.norm(np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]), axis=1).sum()
    assert rest.total_area == pytest.approx(area, rel=1e-12)
    assert rest.total_mass == pytest.approx(COTTON.area_density * area, rel=1e-12)


def test_rest_from_model_equals_from_mesh():
    import warp as wp

    from simgen.sim import ClothModel

    v, f = grid(4, seed=2)
    for mode in ("template", "flat"):
        a = ClothRest.from_mesh(v, f, COTTON, bending_rest=mode, dtype=torch.float64)
        b = ClothRest.from_model(ClothModel.from_mesh(v, f, COTTON, device="cpu", dtype=wp.float64, bending_rest=mode),
                                 dtype=torch.float64)
        for name in ("tri_inv_rest", "tri_area", "vertex_mass", "hinge_stiffness", "hinge_rest_angle"):
            torch.testing.assert_close(getattr(a, name), getattr(b, name), rtol=1e-12, atol=1e-12)
        assert torch.equal(a.hinges, b.hinges) and torch.equal(a.faces, b.faces)


def test_rest_rejects_bad_input():
    v, f = grid(3)
    with pytest.raises(InputError, match="bending_rest"):
        ClothRest.from_mesh(v, f, COTTON, bending_rest="curved")
    with pytest.raises(InputError, match="degenerate"):
        ClothRest.from_mesh(np.zeros((4, 3)), [[0, 1, 2], [0, 2, 3]], COTTON)
    rest = ClothRest.from_mesh(v, f, COTTON)
    with pytest.raises(InputError, match=r"\(\.\.\., 9, 3\)"):
        membrane(torch.zeros(2, 8, 3), rest)


# -- analytic values -------------------------------------------------------------------------------

@pytest.mark.parametrize("stretch", [1.1, 0.95])
def test_membrane_uniaxial_stretch_by_hand(stretch):
    """x -> s x on a flat sheet: G = diag((s^2 - 1) / 2, 0), E = A (lambda h / 2 + mu h) G_xx^2."""
    v, f = grid(4)
    rest = ClothRest.from_mesh(v, f, COTTON, dtype=torch.float64)
    x = torch.tensor(v * np.array([stretch, 1.0, 1.0]))
    gxx = (stretch**2 - 1) / 2
    lam, mu = COTTON.membrane_stiffness
    assert float(membrane(x, rest)) == pytest.approx(0.01 * (lam / 2 + mu) * gxx**2, rel=1e-12)


def test_membrane_matches_frame_free_reference_and_is_rigid_invariant():
    v, f = grid(4, seed=3)
    rest = ClothRest.from_mesh(v, f, COTTON, dtype=torch.float64)
    x = v + 0.004 * np.random.default_rng(4).normal(size=v.shape)
    lam, mu = COTTON.membrane_stiffness
    e_ref, g_ref = ref.membrane(x, v, f, np.full(len(f), lam), np.full(len(f), mu))
    xt = torch.tensor(x)
    assert float(membrane(xt, rest)) == pytest.approx(e_ref.sum(), rel=1e-12)
    torch.testing.assert_close(autograd(lambda y: membrane(y, rest), xt), torch.tensor(g_ref), rtol=1e-9, atol=1e-12)
    from scipy.spatial.transform import Rotation

    R = torch.tensor(Rotation.from_rotvec([0.3, -1.2, 0.7]).as_matrix())
    assert float(membrane(xt @ R.T + torch.tensor([0.5, 1.0, -2.0]), rest)) == pytest.approx(e_ref.sum(), rel=1e-10)
    assert float(membrane(torch.tensor(v), rest)) == pytest.approx(0.0, abs=1e-18)


@pytest.mark.parametrize("phi", [0.3, -1.0, 2.5])
def test_bending_hinge_folded_by_known_angle(phi):
    """Two right triangles folded about their shared edge by phi: E = k phi^2 / 2 (flat rest),
    k = k_bend l^2 / (4 (a1 + a2)) with l = 0.1 m and a1 = a2 = 0.005 m^2."""
    v = np.array([[0.0, 0, 0], [0.0, 0, 0.1], [0.1, 0, 0], [-0.1, 0, 0.1]])
    f = np.array([[0, 1, 2], [0, 3, 1]])
    rest = ClothRest.from_mesh(v, f, COTTON, bending_rest="flat", dtype=torch.float64)
    c, s = math.cos(phi), math.sin(phi)
    x = v.copy()
    x[3] = [-0.1 * c, 0.1 * s, 0.1]       # rotate the wing of face B about the z axis (the edge)
    k = COTTON.bending_stiffness * 0.01 / (4 * 0.01)
    e = float(bending(torch.tensor(x), rest))
    assert e == pytest.approx(k * phi**2 / 2, rel=1e-10)
    # the template rest angle of the folded hinge is phi: no energy at the template
    folded = ClothRest.from_mesh(x, f, COTTON, bending_rest="template", dtype=torch.float64)
    assert float(bending(torch.tensor(x), folded)) == pytest.approx(0.0, abs=1e-20)
    assert float(bending(torch.tensor(v), folded)) == pytest.approx(e, rel=1e-10)


def test_gravity_is_m_g_h_and_datum_shifts_it():
    v, f = grid(4, seed=5)
    rest = ClothRest.from_mesh(v, f, COTTON, dtype=torch.float64)
    x = torch.tensor(v + [0.0, 1.3, 0.0])
    m = rest.vertex_mass
    assert float(gravity(x, rest)) == pytest.approx(float(9.81 * (m * x[:, 1]).sum()), rel=1e-12)
    origin = torch.tensor([0.2, 1.0, -0.3])
    assert float(gravity(x, rest, origin=origin)) == pytest.approx(float(9.81 * (m * (x[:, 1] - 1.0)).sum()),
                                                                   rel=1e-12)
    g = GravityParams((1.0, -9.81, 0.5))
    expected = float(-(m * (x @ torch.tensor(g.gravity, dtype=torch.float64))).sum())
    assert float(gravity(x, rest, g)) == pytest.approx(expected, rel=1e-12)


def test_inertia_of_constant_acceleration():
    """x_t = x_0 + a t^2 / 2: x_t - (2 x_{t-1} - x_{t-2}) = a h^2, so E = M |a|^2 h^2 / 2 per frame."""
    v, f = grid(4, seed=6)
    rest = ClothRest.from_mesh(v, f, COTTON, dtype=torch.float64)
    h, a = 1 / 30, torch.tensor([0.3, -9.81, 1.2], dtype=torch.float64)
    t = torch.arange(6, dtype=torch.float64)[:, None, None] * h
    x = torch.tensor(v)[None] + 0.5 * a * t**2 + torch.tensor([0.5, 0.0, 0.0]) * t
    expected = rest.total_mass * float(a @ a) * h**2 / 2
    e = inertia_sequence(x, rest, h, reduction="none")
    assert e.shape == (4,)
    torch.testing.assert_close(e, torch.full((4,), expected, dtype=torch.float64), rtol=1e-9, atol=0.0)
    assert float(inertia(x[3], predict(x[2], x[1]), rest, h)) == pytest.approx(expected, rel=1e-9)
    # SNUG's window convention: frame 1 predicted with zero velocity (x_hat = x_0)
    first = inertia_sequence(x, rest, h, start="rest", reduction="none")[0]
    d = x[1] - x[0]
    assert float(first) == pytest.approx(float(0.5 / h**2 * (rest.vertex_mass * (d * d).sum(-1)).sum()), rel=1e-12)


# -- gradients, batching, dtypes --------------------------------------------------------------------

@pytest.fixture(scope="module")
def box_scene():
    bv, bf = box()
    surface = BodySurface(bf, bv)
    v, f = grid(6, size=0.18)
    # The sheet over the box's top face and one corner: points inside the margin, inside the body,
    # and beyond the top's edges and corner (edge and vertex regions of the closest point).
    v = v + np.array([-0.03, 0.1005, -0.03])
    rng = np.random.default_rng(8)
    v = v + 0.001 * rng.normal(size=v.shape)
    return surface, torch.tensor(bv), v, f


def test_autograd_matches_finite_differences(box_scene):
    surface, bv, v, f = box_scene
    rest = ClothRest.from_mesh(v, f, COTTON, dtype=torch.float64)
    x = torch.tensor(v) + 1e-3 * torch.randn(len(v), 3, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    x_hat = x + 0.01
    params = ContactParams(margin=3e-3)
    terms = {
        "membrane": lambda y: membrane(y, rest), "bending": lambda y: bending(y, rest),
        "gravity": lambda y: gravity(y, rest), "inertia": lambda y: inertia(y, x_hat, rest, 1 / 30),
        "contact": lambda y: contact(y, bv, surface, params),
    }
    d = body_distance(x, bv, surface)
    assert int(((d.distance > 0) & (d.distance < params.margin)).sum()) > 2 and int((d.distance < 0).sum()) > 2
    tri = bv[surface.faces[d.face]]
    _, _, region = closest_point_triangle(x, tri[:, 0], tri[:, 1], tri[:, 2])
    assert int((region < 3).sum()) > 0 and int(((region >= 3) & (region != REGION_INTERIOR)).sum()) > 0
    for name, fn in terms.items():
        g = autograd(fn, x)
        g_fd = fd_gradient(fn, x.detach())
        scale = float(g.abs().max())
        assert scale > 0, name
        assert float((g - g_fd).abs().max()) <= 1e-5 * scale, name


def test_signed_distance_matches_brute_force_and_winding_numbers(box_scene):
    surface, bv, _, _ = box_scene
    rng = np.random.default_rng(9)
    pts = rng.uniform(-0.15, 0.15, size=(300, 3))
    d = body_distance(torch.tensor(pts), bv, surface).distance.numpy()
    d_ref, _ = ref.signed_distance(pts, bv.numpy(), surface.faces.numpy())
    np.testing.assert_allclose(d, d_ref, atol=1e-12)


def test_nearest_triangle_search_is_exact_on_the_body():
    # The BVH picks its triangle by Warp's float32 distances: as near as the brute force's within float32.
    from simgen.body import load

    body = load("open")
    surface = BodySurface.from_body(body)
    verts = torch.tensor(body.v_template)
    rng = np.random.default_rng(10)
    # points near the surface (the use case) and far from it (wide candidate sets)
    near = body.v_template[rng.integers(0, body.num_vertices, 160)] + 0.01 * rng.normal(size=(160, 3))
    far = rng.uniform(body.v_template.min(0) - 0.3, body.v_template.max(0) + 0.3, size=(24, 3))
    pts = torch.tensor(np.concatenate([near, far]))
    fast = surface.nearest_faces(pts, surface.frame_geometry(verts))
    slow = surface.nearest_faces_brute_force(pts, verts, chunk=16)
    tri = verts[surface.faces]

    def dist(face):
        c, _, _ = closest_point_triangle(pts, tri[face, 0], tri[face, 1], tri[face, 2])
        return (pts - c).norm(dim=1)

    torch.testing.assert_close(dist(fast), dist(slow), rtol=0, atol=1e-6)


def test_nearest_triangle_search_refits_its_meshes_to_each_call():
    # One call builds a mesh per frame, the next refits them to other poses and adds a slot: every
    # answer is as near as the brute force's, within float32.
    from simgen.body import load

    body = load("open")
    surface = BodySurface.from_body(body)
    v = torch.tensor(body.v_template)
    turn = torch.tensor([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]], dtype=v.dtype)
    rng = np.random.default_rng(4)
    pts = torch.tensor(body.v_template[rng.integers(0, body.num_vertices, (3, 40))] + 0.02 * rng.normal(size=(3, 40, 3)))
    for frames in (torch.stack([v, v + 0.1]), torch.stack([v @ turn.T, v * 1.1, v - 0.3])):
        n = len(frames)
        found = surface.nearest_faces(pts[:n], surface.frame_geometry(frames))
        for i in range(n):
            tri = frames[i][surface.faces]
            slow = surface.nearest_faces_brute_force(pts[i], frames[i], chunk=16)

            def dist(face):
                c, _, _ = closest_point_triangle(pts[i], tri[face, 0], tri[face, 1], tri[face, 2])
                return (pts[i] - c).norm(dim=1)

            torch.testing.assert_close(dist(found[i]), dist(slow), rtol=0, atol=1e-6)
    assert len(surface._bvh.slots) == 3


def test_body_distance_over_several_frames_at_once_equals_one_frame_at_a_time():
    # Three bodies (the template, squashed, shifted and turned) in chunks that split the frames give
    # the signed distances of single-frame calls (the triangles may differ where two tie within
    # float32, so the distances agree to float32's resolution).
    from simgen.body import load
    from simgen.physics.surface_query import body_distance

    body = load("open")
    surface = BodySurface.from_body(body)
    v = torch.tensor(body.v_template)
    turn = torch.tensor([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]], dtype=v.dtype)
    frames = torch.stack([v, v * torch.tensor([1.2, 0.9, 1.1], dtype=v.dtype), v @ turn.T + 0.05])
    rng = np.random.default_rng(3)
    pts = torch.tensor(body.v_template[rng.integers(0, body.num_vertices, (3, 90))] + 0.02 * rng.normal(size=(3, 90, 3)))
    together = body_distance(pts, frames, surface, frames_at_once=2)
    apart = [body_distance(pts[i], frames[i], surface) for i in range(3)]
    torch.testing.assert_close(together.distance, torch.stack([a.distance for a in apart]), rtol=0, atol=1e-6)


def test_batched_terms_equal_per_frame_and_reductions(box_scene):
    surface, bv, v, f = box_scene
    rest = ClothRest.from_mesh(v, f, COTTON, dtype=torch.float64)
    gen = torch.Generator().manual_seed(1)
    x = torch.tensor(v) + 2e-3 * torch.randn((2, 3, len(v), 3), generator=gen, dtype=torch.float64)
    bodies = bv + 1e-3 * torch.randn((2, 3, 1, 3), generator=gen, dtype=torch.float64)
    for fn in (lambda y, b: membrane(y, rest, reduction="none"), lambda y, b: bending(y, rest, reduction="none"),
               lambda y, b: gravity(y, rest, reduction="none"),
               lambda y, b: contact(y, b, surface, ContactParams(), reduction="none")):
        batched = fn(x, bodies)
        assert batched.shape == (2, 3)
        for i in range(2):
            for t in range(3):
                assert float(batched[i, t]) == pytest.approx(float(fn(x[i, t], bodies[i, t])), rel=1e-12, abs=1e-20)
    e = membrane(x, rest, reduction="none")
    assert float(membrane(x, rest)) == pytest.approx(float(e.mean()), rel=1e-12)
    assert float(membrane(x, rest, reduction="sum")) == pytest.approx(float(e.sum()), rel=1e-12)
    with pytest.raises(InputError, match="reduction"):
        membrane(x, rest, reduction="max")


def test_float32_agrees_with_float64(box_scene):
    surface, bv, v, f = box_scene
    r64 = ClothRest.from_mesh(v, f, COTTON, dtype=torch.float64)
    r32 = r64.to(dtype=torch.float32)
    gen = torch.Generator().manual_seed(2)
    x = torch.tensor(v) + 2e-3 * torch.randn((len(v), 3), generator=gen, dtype=torch.float64)
    for fn, rel in ((membrane, 1e-3), (bending, 1e-3), (gravity, 1e-6)):
        assert float(fn(x.float(), r32)) == pytest.approx(float(fn(x, r64)), rel=rel)
    c64 = float(contact(x, bv, surface))
    assert float(contact(x.float(), bv.float(), surface)) == pytest.approx(c64, rel=1e-3)


def test_snug_loss_and_incremental_potential(box_scene):
    surface, bv, v, f = box_scene
    rest = ClothRest.from_mesh(v, f, COTTON, dtype=torch.float64)
    gen = torch.Generator().manual_seed(3)
    x = (torch.tensor(v) + 1e-3 * torch.randn((2, 3, len(v), 3), generator=gen, dtype=torch.float64)).requires_grad_()
    loss = snug_loss(x, rest, 1 / 30, bv.expand(2, 3, -1, -1), surface)
    loss["total"].backward()
    loss = {k: float(v.detach()) for k, v in loss.items()}
    assert loss["contact"] == pytest.approx(float(contact(x.detach(), bv, surface, ContactParams.snug())), rel=1e-12)
    parts = ("membrane", "bending", "gravity", "contact", "inertia")
    assert loss["total"] == pytest.approx(sum(loss[k] for k in parts), rel=1e-12)
    assert torch.isfinite(x.grad).all() and float(x.grad.abs().max()) > 0
    x = x.detach()
    ip = incremental_potential(x[0, 2], x[0, 1], x[0, 0], rest, 1 / 30, bv, surface)
    assert float(ip["total"]) == pytest.approx(sum(float(ip[k]) for k in ip if k != "total"), rel=1e-12)
    assert float(ip["inertia"]) == pytest.approx(float(inertia_sequence(x[0], rest, 1 / 30)), rel=1e-12)


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_cuda_equals_cpu(box_scene):
    surface, bv, v, f = box_scene
    rest = ClothRest.from_mesh(v, f, COTTON, dtype=torch.float64)
    gen = torch.Generator().manual_seed(4)
    x = torch.tensor(v) + 2e-3 * torch.randn((2, len(v), 3), generator=gen, dtype=torch.float64)
    cpu = [float(membrane(x, rest)), float(bending(x, rest)), float(gravity(x, rest)), float(contact(x, bv, surface))]
    rc, sc = rest.to(device="cuda"), BodySurface(surface.faces.numpy(), bv.numpy()).to("cuda")
    xc, bc = x.cuda().requires_grad_(), bv.cuda()
    gpu = [membrane(xc, rc), bending(xc, rc), gravity(xc, rc), contact(xc, bc, sc)]
    sum(gpu).backward()
    assert torch.isfinite(xc.grad).all()
    for a, b in zip(cpu, gpu):
        assert float(b) == pytest.approx(a, rel=1e-9, abs=1e-15)
