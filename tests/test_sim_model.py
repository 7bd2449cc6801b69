"""Cloth model, materials and topology of the Warp solver (simgen.sim)."""

import numpy as np
import pytest
import warp as wp

from simgen.errors import InputError
from simgen.garment.garment import Garment
from simgen.sim import MATERIALS, ClothModel, ClothModelBuilder, Material, get_material
from simgen.sim.energies import eval_bending, eval_gravity, eval_membrane
from simgen.sim.energies import reference as ref
from simgen.topology import build_bsr_pattern, extract_hinges, stack_bsr_patterns

wp.config.quiet = True


def grid(n=4, size=0.1):
    """A flat n x n vertex grid in the xz plane (Y-up), two triangles per cell."""
    xs = np.linspace(0.0, size, n)
    X, Z = np.meshgrid(xs, xs, indexing="ij")
    v = np.stack([X.ravel(), np.zeros(n * n), Z.ravel()], axis=1)
    f = []
    for i in range(n - 1):
        for j in range(n - 1):
            a, b, c, d = i * n + j, (i + 1) * n + j, (i + 1) * n + j + 1, i * n + j + 1
            f += [[a, d, c], [a, c, b]]
    return v, np.array(f)


def crumpled(n=4, seed=0):
    v, f = grid(n)
    return v + 0.005 * np.random.default_rng(seed).normal(size=v.shape), f


# -- materials --------------------------------------------------------------------------------------

def test_snug_cotton_lame_parameters_match_the_thesis():
    cotton = get_material("snug_cotton")
    assert cotton.lame_lambda == pytest.approx(4.44e4, rel=5e-3)
    assert cotton.lame_mu == pytest.approx(2.36e4, rel=5e-3)
    assert cotton.area_density == 0.2 and cotton.thickness == 4.7e-4 and cotton.bending_stiffness == 3.96e-5
    assert cotton.friction_coefficient == 0.3
    lam_h, mu_h = cotton.membrane_stiffness
    assert lam_h == pytest.approx(cotton.lame_lambda * 4.7e-4) and mu_h == pytest.approx(cotton.lame_mu * 4.7e-4)


def test_presets_have_sources_and_expected_densities():
    assert set(MATERIALS) == {"cotton", "interlock", "snug_cotton", "denim", "silk"}
    assert MATERIALS["interlock"].area_density == 0.187
    assert MATERIALS["denim"].area_density == 0.324
    assert 0.05 <= MATERIALS["silk"].area_density <= 0.08
    denim, cotton, silk = MATERIALS["denim"], MATERIALS["cotton"], MATERIALS["silk"]
    assert denim.stretch_stiffness_2d > cotton.stretch_stiffness_2d
    assert denim.bending_stiffness > cotton.bending_stiffness > silk.bending_stiffness
    for m in MATERIALS.values():
        assert len(m.source) > 20
        assert Material.from_dict(m.to_dict()) == m


def _flat_grid(n, h, equilateral):
    """A flat n x n patch [m] of spacing h: right triangles, or equilateral ones (rows offset by h/2)."""
    rows = np.sqrt(3.0) / 2.0 if equilateral else 1.0
    v = np.array([(i * h + (0.5 * h * (j % 2) if equilateral else 0.0), j * h * rows, 0.0)
                  for j in range(n + 1) for i in range(n + 1)])
    f = []
    for j in range(n):
        for i in range(n):
            a, b, c, d = j * (n + 1) + i, j * (n + 1) + i + 1, (j + 1) * (n + 1) + i, (j + 1) * (n + 1) + i + 1
            f += [(a, b, c), (b, d, c)] if equilateral and j % 2 == 0 else [(a, d, c), (a, b, d)]
    return v, np.array(f)


@pytest.mark.parametrize("equilateral", [False, True])
@pytest.mark.parametrize("axis", [0, 1])
def test_flexural_rigidity_is_the_plate_limit_of_the_hinge_energy(equilateral, axis):
    """A patch rolled onto a cylinder of curvature kappa stores the plate energy B kappa^2 / 2 per
    area with B = material.flexural_rigidity (= k_bend / 4), to the boundary hinges' share."""
    import torch

    from simgen.physics import ClothRest
    from simgen.physics.bending import bending

    v, f = _flat_grid(40, 0.005, equilateral)
    rest = ClothRest.from_mesh(v, f, "interlock", bending_rest="flat", dtype=torch.float64)
    radius = 0.25
    u, w = v[:, axis], v[:, 1 - axis]
    rolled = np.stack([radius * np.sin(u / radius), w, radius * (1.0 - np.cos(u / radius))], axis=1)
    energy = float(bending(torch.as_tensor(rolled), rest, reduction="sum"))
    area = 0.5 * np.linalg.norm(np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]), axis=1).sum()
    plate = get_material("interlock").flexural_rigidity * area / (2.0 * radius**2)
    assert energy / plate == pytest.approx(1.0, abs=0.03)  # 40 x 40: boundary hinges are missing ~1.7%


def test_unknown_preset_lists_names():
    with pytest.raises(InputError, match="cotton.*interlock.*denim.*silk"):
        get_material("velvet")
    assert get_material("Denim") is MATERIALS["denim"]


def test_material_overrides_are_validated():
    cotton = get_material("cotton")
    e = cotton.youngs_modulus
    stiff = cotton.with_overrides(youngs_modulus=2 * e, friction_coefficient=0.0, damping_stiffness=1e-3)
    assert stiff.lame_mu == pytest.approx(2 * cotton.lame_mu) and stiff.friction_coefficient == 0.0
    assert get_material("cotton").youngs_modulus == e  # the preset is untouched
    with pytest.raises(InputError, match="youngs_modulsu"):
        cotton.with_overrides(youngs_modulsu=1.0)
    for field in ("area_density", "youngs_modulus", "thickness", "bending_stiffness"):
        for bad in (0.0, -1.0):
            with pytest.raises(InputError, match=field):
                cotton.with_overrides(**{field: bad})
    for field in ("friction_coefficient", "damping_stiffness", "damping_mass"):
        with pytest.raises(InputError, match=field):
            cotton.with_overrides(**{field: -0.1})
    with pytest.raises(InputError, match="poisson_ratio"):
        cotton.with_overrides(poisson_ratio=1.0)
    with pytest.raises(InputError, match="thickness"):
        cotton.with_overrides(thickness=float("nan"))
    with pytest.raises(InputError, match="area_density"):
        cotton.with_overrides(area_density="heavy")


# -- topology ---------------------------------------------------------------------------------------

def test_hinges_of_a_grid_are_its_interior_edges_oriented_by_face_a():
    v, f = grid(4)
    hinges, hinge_faces = extract_hinges(f)
    edges = {tuple(sorted(e)) for tri in f for e in ((tri[0], tri[1]), (tri[1], tri[2]), (tri[2], tri[0]))}
    boundary = 4 * 3
    assert len(hinges) == len(edges) - boundary == 21  # 33 edges of a 3 x 3-cell grid, 12 on the boundary
    for (x0, x1, x2, x3), (fa, fb) in zip(hinges, hinge_faces):
        a, b = f[fa], f[fb]
        k = list(a).index(x0)
        assert a[(k + 1) % 3] == x1 and a[(k + 2) % 3] == x2  # A's cyclic order is (x0, x1, x2)
        assert set(b) == {x0, x1, x3}
    assert np.allclose(ref.dihedral_angles(v, hinges), 0.0)  # flat, consistently oriented
    assert len(extract_hinges(f[:1])[0]) == 0  # a lone triangle has no hinge


def test_non_manifold_edge_is_rejected():
    f = np.array([[0, 1, 2], [1, 0, 3], [0, 1, 4]])
    with pytest.raises(InputError, match="not manifold"):
        extract_hinges(f)


def test_bsr_pattern_holds_exactly_the_coupled_pairs():
    v, f = crumpled(4)
    hinges, _ = extract_hinges(f)
    p = build_bsr_pattern(len(v), f, hinges)
    expected = {(i, i) for i in range(len(v))}
    for elem in list(f) + list(hinges):
        expected |= {(int(a), int(b)) for a in elem for b in elem}
    got = set(zip(p.rows.tolist(), p.columns.tolist()))
    assert got == expected and p.nnz == len(expected)
    assert np.all(np.diff(p.offsets) >= 1) and p.offsets[-1] == p.nnz
    for r in range(len(v)):  # CSR: rows contiguous, columns sorted
        cols = p.columns[p.offsets[r]:p.offsets[r + 1]]
        assert np.all(np.diff(cols) > 0) and np.all(p.rows[p.offsets[r]:p.offsets[r + 1]] == r)
    # slot maps point at the right blocks
    for t, tri in enumerate(f):
        for a in range(3):
            for b in range(3):
                s = p.tri_slots[t, 3 * a + b]
                assert (p.rows[s], p.columns[s]) == (tri[a], tri[b])
    for e, h in enumerate(hinges):
        for a in range(4):
            for b in range(4):
                s = p.hinge_slots[e, 4 * a + b]
                assert (p.rows[s], p.columns[s]) == (h[a], h[b])
    assert np.all(p.rows[p.diag_slots] == np.arange(len(v))) and np.all(p.columns[p.diag_slots] == np.arange(len(v)))
    # wings of a hinge couple although they share no triangle
    x2, x3 = hinges[0][2], hinges[0][3]
    assert not any({x2, x3} <= set(tri) for tri in f) and (x2, x3) in got


def test_stacked_patterns_equal_the_pattern_of_the_concatenated_meshes():
    # A pool's model stacks one pattern per slot; it must be the pattern built from scratch.
    meshes = [crumpled(3), crumpled(4), crumpled(3)]
    faces, hinges, parts, off = [], [], [], 0
    for v, f in meshes:
        h, _ = extract_hinges(f)
        parts.append(build_bsr_pattern(len(v), f, h))
        faces.append(f + off)
        hinges.append(h + off)
        off += len(v)
    whole = build_bsr_pattern(off, np.concatenate(faces), np.concatenate(hinges))
    stacked = stack_bsr_patterns(parts)
    assert stacked.num_vertices == whole.num_vertices
    for name in ("offsets", "columns", "rows", "diag_slots", "tri_slots", "hinge_slots"):
        a, b = getattr(stacked, name), getattr(whole, name)
        assert a.dtype == b.dtype and np.array_equal(a, b), name


def test_warp_bsr_matrix_uses_the_pattern():
    v, f = crumpled(3)
    m = ClothModel.from_mesh(v, f, "cotton", device="cpu")
    h = m.new_hessian()
    assert h.nnz_sync() == m.nnz
    assert np.array_equal(h.offsets.numpy()[: m.num_vertices + 1], m.pattern.offsets)
    assert np.array_equal(h.columns.numpy()[: m.nnz], m.pattern.columns)
    assert h.values.dtype == wp.mat33 and np.abs(h.values.numpy()).max() == 0.0


# -- model ------------------------------------------------------------------------------------------

def test_lumped_masses_rest_frames_and_hinge_coefficients():
    v, f = crumpled(4)
    m = ClothModel.from_mesh(v, f, "denim", device="cpu", dtype=wp.float64)
    area = 0.5 * np.linalg.norm(np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]), axis=1)
    assert np.allclose(m.host.tri_rest_area, area, rtol=1e-12)
    assert m.vertex_mass.numpy().sum() == pytest.approx(area.sum() * 0.324, rel=1e-12)
    expected = np.zeros(len(v))
    np.add.at(expected, f.reshape(-1), np.repeat(area / 3.0, 3) * 0.324)
    assert np.allclose(m.host.vertex_mass, expected, rtol=1e-12)
    # Dm^-1 maps the rest edges to an isometry: F^T F = I at rest
    for t, tri in enumerate(f):
        ds = np.stack([v[tri[1]] - v[tri[0]], v[tri[2]] - v[tri[0]]], axis=1)
        F = ds @ m.host.tri_inv_rest[t]
        assert np.allclose(F.T @ F, np.eye(2), atol=1e-12)
    assert np.allclose(m.tri_inv_rest.numpy(), m.host.tri_inv_rest)
    denim = get_material("denim")
    assert np.allclose(m.tri_lambda.numpy(), denim.membrane_stiffness[0])
    assert np.allclose(m.tri_mu.numpy(), denim.membrane_stiffness[1])
    h, hf = m.host.hinges[5], m.host.hinge_faces[5]
    l2 = np.sum((v[h[1]] - v[h[0]]) ** 2)
    assert m.host.hinge_stiffness[5] == pytest.approx(denim.bending_stiffness * l2 / (4 * (area[hf[0]] + area[hf[1]])))
    assert np.allclose(m.hinge_rest_angle.numpy(), ref.dihedral_angles(v, m.host.hinges))
    assert np.all(m.vertex_friction.numpy() == denim.friction_coefficient)


def test_state_pins_and_types():
    v, f = crumpled(3)
    m = ClothModel.from_mesh(v, f, "cotton", pinned=[0, 2], device="cpu")
    assert m.scalar is wp.float32 and m.rest_positions.dtype == wp.vec3
    s = m.state()
    assert s.positions.shape == (9,) and s.velocities.dtype == wp.vec3
    assert np.allclose(s.positions.numpy(), v, atol=1e-7) and not s.velocities.numpy().any()
    s2 = s.clone()
    s.positions.fill_(1.0)
    assert np.allclose(s2.positions.numpy(), v, atol=1e-7)
    s.assign(s2)
    assert np.allclose(s.positions.numpy(), v, atol=1e-7)
    assert m.vertex_pinned.numpy().tolist() == [1, 0, 1, 0, 0, 0, 0, 0, 0]
    mask = np.zeros(9, dtype=bool)
    mask[4] = True
    assert ClothModel.from_mesh(v, f, "cotton", pinned=mask, device="cpu").vertex_pinned.numpy()[4] == 1
    m64 = ClothModel.from_mesh(v, f, "cotton", device="cpu", dtype=wp.float64)
    assert m64.state().positions.dtype == wp.vec3d and m64.new_hessian().values.dtype == wp.mat33d


def test_invalid_meshes_name_the_problem():
    v, f = grid(3)
    with pytest.raises(InputError, match="degenerate"):
        # vertex 9 on the line through vertices 0 and 3: triangle (0, 3, 9) has no area
        ClothModel.from_mesh(np.r_[v, [[0.2, 0.0, 0.0]]], np.r_[f, [[0, 3, 9]]], "cotton", device="cpu")
    with pytest.raises(InputError, match="belongs to no triangle"):
        ClothModel.from_mesh(np.r_[v, [[1.0, 1.0, 1.0]]], f, "cotton", device="cpu")
    with pytest.raises(InputError, match="bending_rest"):
        ClothModel.from_mesh(v, f, "cotton", bending_rest="curved", device="cpu")
    with pytest.raises(InputError, match="faces index"):
        ClothModel.from_mesh(v, f + 1, "cotton", device="cpu")
    with pytest.raises(InputError, match="unknown material"):
        ClothModel.from_mesh(v, f, "velvet", device="cpu")
    with pytest.raises(InputError, match="pinned"):
        ClothModel.from_mesh(v, f, "cotton", pinned=[42], device="cpu")
    with pytest.raises(InputError, match="no instance"):
        ClothModelBuilder().finalize("cpu")


def test_from_garment_uses_default_material_or_cotton():
    v, f = crumpled(3)
    w = np.zeros((9, 24))
    w[:, 0] = 1.0
    g = Garment("patch", v, f, w, metadata={})
    assert ClothModel.from_garment(g, device="cpu").instances[0].material.name == "cotton"
    g = Garment("patch", v, f, w, metadata={"default_material": "denim"})
    m = ClothModel.from_garment(g, device="cpu")
    assert m.instances[0].material.name == "denim" and m.instances[0].name == "patch"
    assert ClothModel.from_garment(g, "silk", device="cpu").instances[0].material.name == "silk"


def test_two_instances_are_uncoupled_and_keep_their_materials():
    v1, f1 = crumpled(3, seed=1)
    v2, f2 = crumpled(4, seed=2)
    silk = get_material("silk").with_overrides(damping_mass=0.2)
    a = ClothModel.from_mesh(v1, f1, "cotton", device="cpu", dtype=wp.float64)
    b = ClothModel.from_mesh(v2, f2, silk, bending_rest="flat", device="cpu", dtype=wp.float64)
    m = ClothModel.concatenate([a, b])
    assert (m.num_instances, m.num_vertices, m.num_triangles) == (2, 25, 8 + 18)
    assert m.vertex_start.tolist() == [0, 9, 25] and m.instance_slice(1) == slice(9, 25)
    inst = m.host.vertex_instance
    assert np.all(inst[m.pattern.rows] == inst[m.pattern.columns])  # no block couples instances
    assert m.nnz == a.nnz + b.nnz
    assert np.allclose(m.host.vertex_mass[:9], a.host.vertex_mass)
    assert np.allclose(m.host.vertex_mass[9:], b.host.vertex_mass)
    assert np.all(m.host.tri_mu[m.host.tri_instance == 1] == silk.membrane_stiffness[1])
    assert np.all(m.host.hinge_rest_angle[m.host.hinge_instance == 1] == 0.0)
    assert np.all(m.host.vertex_damping_mass[9:] == 0.2) and np.all(m.host.vertex_damping_mass[:9] == 0.0)
    # energies land in each instance's slot and equal the single-instance values
    rng = np.random.default_rng(3)
    x = m.host.rest_positions * 1.05 + 0.002 * rng.normal(size=(25, 3))
    for term in (eval_membrane, eval_bending, eval_gravity):
        e = m.new_energy()
        term(m, wp.array(x, dtype=wp.vec3d, device="cpu"), energy=e)
        ea, eb = a.new_energy(), b.new_energy()
        term(a, wp.array(x[:9], dtype=wp.vec3d, device="cpu"), energy=ea)
        term(b, wp.array(x[9:], dtype=wp.vec3d, device="cpu"), energy=eb)
        assert e.numpy() == pytest.approx([ea.numpy()[0], eb.numpy()[0]], rel=1e-12)
    # a builder gives the same model
    builder = ClothModelBuilder()
    builder.add_instance(v1, f1, "cotton")
    builder.add_instance(v2, f2, silk, bending_rest="flat")
    m2 = builder.finalize("cpu", dtype=wp.float64)
    assert np.array_equal(m2.pattern.columns, m.pattern.columns)
    assert np.array_equal(m2.host.hinge_stiffness, m.host.hinge_stiffness)


def test_a_repeated_model_concatenates_to_what_a_builder_of_its_copies_gives():
    """A pool's model repeats one instance (its rest geometry computed once): every host array and the
    pattern equal, bit for bit, those of a builder given each copy anew."""
    v1, f1 = crumpled(3, seed=1)
    v2, f2 = crumpled(4, seed=2)
    a = ClothModel.from_mesh(v1, f1, "cotton", device="cpu")
    b = ClothModel.from_mesh(v2, f2, "silk", bending_rest="flat", device="cpu")
    m = ClothModel.concatenate([a, b, a, a])
    builder = ClothModelBuilder()
    for v, f, mat, rest in ((v1, f1, "cotton", "template"), (v2, f2, "silk", "flat"), (v1, f1, "cotton", "template"),
                            (v1, f1, "cotton", "template")):
        builder.add_instance(v, f, mat, bending_rest=rest)
    fresh = builder.finalize("cpu")
    for name, value in vars(fresh.host).items():
        assert np.array_equal(getattr(m.host, name), value), name
    for name in ("offsets", "columns", "rows", "diag_slots", "tri_slots", "hinge_slots"):
        assert np.array_equal(getattr(m.pattern, name), getattr(fresh.pattern, name)), name
    assert np.any(m.host.hinge_rest_angle != 0.0)   # the template's angles, the flat one's zero
