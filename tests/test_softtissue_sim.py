"""The soft-tissue simulation (simgen.softtissue): linear elasticity and the Newmark integrator
against the analytic shear layer on a slab, energy conservation, invariants of the driven body
(a still or uniformly moving body does not jiggle), the low-pass on the skeleton, the modal range
of belly and chest, and the flesh mesh (built, bundled, carried to other shapes).

CPU, small: a 6 x 12 x 12 slab and the bundled open-body mesh (4,930 nodes).
"""

import numpy as np
import pytest
import warp as wp

from simgen.errors import InputError
from simgen.softtissue import FleshParams
from simgen.softtissue.elastic import rest_shape
from simgen.softtissue.model import FleshModel
from simgen.softtissue.modes import modal_frequencies, stiffness_matrix
from simgen.softtissue.solver import FleshSolver

wp.config.quiet = True
H, E, NU, RHO, G = 0.03, 2000.0, 0.4, 1000.0, 9.81
MU = E / (2 * (1 + NU))


def _slab(n=(6, 12, 12), size=(H, 0.3, 0.3)):
    """A box of tetrahedra (6 per cell), nodes (N, 3) and tets (T, 4) positively oriented."""
    axes = [np.linspace(0, s, k + 1) for s, k in zip(size, n)]
    grid = np.stack(np.meshgrid(*axes, indexing="ij"), -1)
    idx = np.arange(grid[..., 0].size).reshape(grid.shape[:3])
    corners = np.stack([idx[a:a + n[0], b:b + n[1], c:c + n[2]].ravel()
                        for a in (0, 1) for b in (0, 1) for c in (0, 1)], axis=1)
    split = [[0, 1, 3, 7], [0, 3, 2, 7], [0, 2, 6, 7], [0, 6, 4, 7], [0, 4, 5, 7], [0, 5, 1, 7]]
    tets = corners[:, split].reshape(-1, 4)
    x = grid.reshape(-1, 3)
    _, vol = rest_shape(x, tets)
    tets[vol < 0] = tets[vol < 0][:, [1, 0, 2, 3]]
    return x, tets


@pytest.fixture(scope="module")
def slab():
    """The slab on a wall (x = 0 pinned), free elsewhere, no damping."""
    x, tets = _slab()
    params = FleshParams(poisson=NU, density=RHO, damping_stiffness=0.0)
    model = FleshModel(tets, [x], [x[:, 0] < 1e-9], np.full(len(tets), E), params, device="cpu")
    centre = (np.abs(x[:, 1] - 0.15) < 0.03) & (np.abs(x[:, 2] - 0.15) < 0.03) & (x[:, 0] > H - 1e-9)
    return model, x, centre


def _gravity_along_wall(model):
    f = np.zeros((model.total_nodes, 3), dtype=np.float32)
    f[:, 1] = -model.mass[0] * G
    return f


def test_slab_sags_and_rings_like_the_shear_layer(slab):
    """A layer of thickness h on a wall with gravity along it: u = rho g (h x - x^2 / 2) / mu, so the
    surface sags rho g h^2 / (2 mu); its first mode is the quarter-wave shear f = sqrt(mu / rho) / (4 h)."""
    model, x, centre = slab
    solver = FleshSolver(model)
    solver.static(wp.array(_gravity_along_wall(model), dtype=wp.vec3, device="cpu"))
    sag = solver.u.numpy()[centre, 1].mean()
    assert sag == pytest.approx(-RHO * G * H * H / (2 * MU), rel=0.03)
    freqs, _ = modal_frequencies(solver, count=3)
    assert freqs[0] == pytest.approx(np.sqrt(MU / RHO) / (4 * H), rel=0.05)


def test_energy_is_conserved_without_damping_and_lost_with_it(slab):
    """Released from its sag, the undamped slab keeps its energy (the trapezoidal rule); with
    Rayleigh damping the energy only falls."""
    model, x, centre = slab
    f = wp.array(_gravity_along_wall(model), dtype=wp.vec3, device="cpu")
    zero = wp.zeros(model.total_nodes, dtype=wp.vec3, device="cpu")
    energies = {}
    for damping in (0.0, 5e-3):
        model.params = FleshParams(poisson=NU, density=RHO, damping_stiffness=damping)
        solver = FleshSolver(model)
        solver.static(f)
        e = [solver.energy()[0]]
        moved = []
        for _ in range(120):
            solver.step(zero, 1.0 / 960.0)
            e.append(solver.energy()[0])
            moved.append(solver.u.numpy()[centre, 1].mean())
        energies[damping] = np.array(e)
        assert max(moved) > 0.5 * -min(moved)  # it swings through the rest state
    e = energies[0.0]
    assert np.abs(e - e[0]).max() < 2e-3 * e[0]
    d = energies[5e-3]
    assert np.all(np.diff(d) < 1e-6 * d[0]) and d[-1] < 0.5 * d[0]


def test_stiffness_read_back_matches_the_diagonal_kernel(slab):
    model, _, _ = slab
    solver = FleshSolver(model)
    K = stiffness_matrix(solver)
    assert abs(K - K.T).max() < 1e-4 * abs(K).max()
    blocks = np.stack([K[3 * i:3 * i + 3, 3 * i:3 * i + 3].toarray() for i in range(model.num_nodes)])
    np.testing.assert_allclose(blocks, solver.diag.numpy(), rtol=1e-4, atol=1e-6 * abs(K).max())


@pytest.fixture(scope="module")
def body():
    from simgen import body as body_pkg

    return body_pkg.load("open")


def _clip(name, trans):
    from simgen.motion.clip import MotionClip

    return MotionClip(name, 60.0, np.zeros((len(trans), 24, 3)), np.asarray(trans, dtype=np.float64), {})


def test_a_still_or_uniformly_moving_body_does_not_jiggle(body):
    """Gravity off: a body held still or moving at constant velocity leaves u = 0. With gravity the
    flesh hangs at the pose's static equilibrium and stays there."""
    from simgen.softtissue import simulate_softtissue

    T = 8
    still = _clip("still", np.tile([0.0, 0.9, 0.0], (T, 1)))
    glide = _clip("glide", np.stack([np.arange(T) * 0.03, np.full(T, 0.9), np.arange(T) * 0.01], axis=1))
    for clip in (still, glide):
        (seq,) = simulate_softtissue(body, clip, params=FleshParams(gravity=0.0))
        assert np.abs(seq.displacements).max() < 1e-9, clip.name
    (seq,) = simulate_softtissue(body, still)
    d = seq.displacements
    assert np.linalg.norm(d[0], axis=1).max() > 2e-3                 # it does hang
    assert np.abs(d - d[:1]).max() < 1e-2 * np.abs(d[0]).max()       # and stays
    assert seq.meta["min_det"] > 0.9


def test_gravity_and_spin_act_in_the_nodes_frame(body):
    """The load is m R^T (g - a) in each node's frame: a body held upside down hangs the other way
    (u flips exactly: the system is linear), and a body spinning about its vertical axis (gravity
    off) pushes the belly out to the front and the back out to the back (centrifugal)."""
    from simgen.softtissue import REGIONS, flesh_mesh, simulate_softtissue

    T = 6
    up = _clip("up", np.tile([0.0, 0.9, 0.0], (T, 1)))
    flipped = _clip("flipped", np.tile([0.0, 0.9, 0.0], (T, 1)))
    flipped.poses[:, 0] = [0.0, 0.0, np.pi]                    # root turned half a turn about z
    (a,) = simulate_softtissue(body, up)
    (b,) = simulate_softtissue(body, flipped)
    scale = np.abs(a.displacements[0]).max()
    assert scale > 2e-3
    np.testing.assert_allclose(b.displacements[0], -a.displacements[0], atol=1e-3 * scale)

    spin = _clip("spin", np.tile([0.0, 0.9, 0.0], (10, 1)))
    omega = 2 * np.pi                                          # one turn per second about y
    spin.poses[:, 0] = np.stack([np.zeros(10), omega * np.arange(10) / 60.0, np.zeros(10)], axis=1)
    (c,) = simulate_softtissue(body, spin, params=FleshParams(gravity=0.0))
    region = flesh_mesh(body).region[flesh_mesh(body).skin_tet]
    out = body.v_template - body.rest_joints()[0][0]                    # from the spin's axis (pelvis)
    out[:, 1] = 0.0
    out /= np.linalg.norm(out, axis=1, keepdims=True)
    d = c.displacements.astype(np.float64)
    for name in ("belly", "chest", "buttocks", "upper_arm"):
        sel = region == REGIONS.index(name)
        radial = np.einsum("tvc,vc->tv", d[:, sel], out[sel]).mean(axis=1)
        assert np.all(radial > 1e-4), (name, radial)                    # pushed outwards
        assert np.ptp(radial) < 0.3 * radial.mean(), (name, radial)     # steadily: the spin is uniform


def test_shapes_batched_in_one_system_equal_their_runs_alone(body):
    from simgen.softtissue import simulate_softtissue

    clip = _clip("sway", np.stack([0.02 * np.sin(np.arange(8) / 3.0), np.full(8, 0.9), np.zeros(8)], axis=1))
    betas = np.zeros((2, body.num_betas))
    betas[1, 2] = 2.0
    both = simulate_softtissue(body, clip, betas)
    (alone,) = simulate_softtissue(body, clip, betas[1:])
    assert np.abs(both[1].displacements).max() > 1e-3
    np.testing.assert_allclose(both[1].displacements, alone.displacements, atol=1e-6)
    assert both[1].meta["layer_m"] > both[0].meta["layer_m"]         # the heavier shape's layer is thicker


def test_clips_batched_in_one_system_equal_their_runs_alone(body):
    # The dataset generator's unit: several clips (of different lengths) and shapes in one system.
    # The PCG runs per instance until every one has converged, so a batch differs from the runs alone
    # only within the solver's tolerance.
    from simgen.softtissue import simulate_softtissue
    from simgen.softtissue.simulate import simulate_softtissue_jobs

    sway = _clip("sway", np.stack([0.02 * np.sin(np.arange(8) / 3.0), np.full(8, 0.9), np.zeros(8)], axis=1))
    hop = _clip("hop", np.stack([np.zeros(5), 0.9 + 0.03 * np.sin(np.arange(5) / 1.5), np.zeros(5)], axis=1))
    heavy = np.zeros(body.num_betas)
    heavy[2] = 2.0
    batch = simulate_softtissue_jobs(body, [(sway, heavy, "heavy"), (hop, np.zeros(body.num_betas), "zero")])
    (a,) = simulate_softtissue(body, sway, heavy[None], subjects=["heavy"])
    (b,) = simulate_softtissue(body, hop)
    for got, alone in ((batch[0], a), (batch[1], b)):
        assert got.num_frames == alone.num_frames and got.motion == alone.motion
        scale = np.abs(alone.displacements).max()
        assert scale > 1e-3
        np.testing.assert_allclose(got.displacements, alone.displacements, atol=2e-3 * scale)
        assert got.meta["min_det"] == pytest.approx(alone.meta["min_det"], abs=1e-4)
    assert batch[0].num_frames == 8 and batch[1].num_frames == 5 and batch[1].subject == "zero"


def test_the_inversion_measure_is_det_of_the_deformation_gradient(slab):
    # u = G x on every node: det(I + grad u) = det(I + G) on every tetrahedron, whatever its shape.
    from simgen.softtissue.simulate import _tet_min_det

    model, x, _ = slab
    Gm = np.array([[0.1, 0.3, 0.0], [-0.2, -0.4, 0.05], [0.0, 0.1, 0.2]])
    u = wp.array((x @ Gm.T).astype(np.float32), dtype=wp.vec3, device="cpu")
    out = wp.full(1, 1e30, dtype=wp.float32, device="cpu")
    wp.launch(_tet_min_det, dim=model.num_tets_total, device="cpu",
              inputs=[u, model.tets, model.inv_rest, model.num_tets_total], outputs=[out])
    assert out.numpy()[0] == pytest.approx(np.linalg.det(np.eye(3) + Gm), rel=1e-4)


def test_the_skeleton_is_low_passed_before_it_is_differenced(body):
    """30 Hz jitter of 1 mm on the root (an acceleration of 36 m/s^2 if differenced raw) is removed by
    the 12 Hz low-pass; the 1 Hz sway under it keeps its acceleration."""
    from simgen.softtissue import skeleton_tracks

    t = np.arange(120) / 60.0
    sway = 0.05 * np.sin(2 * np.pi * 1.0 * t)
    jitter = 0.001 * np.sin(2 * np.pi * 30.0 * t)
    clip = _clip("jitter", np.stack([sway + jitter, np.full_like(t, 0.9), np.zeros_like(t)], axis=1))
    A, dd, fine = skeleton_tracks(body, clip, np.zeros((1, body.num_betas)), FleshParams())
    acc = dd[:, 0, 0, 0, 3]                                          # root x acceleration [m/s^2]
    tf = np.arange(len(acc)) / 240.0
    expected = -0.05 * (2 * np.pi) ** 2 * np.sin(2 * np.pi * tf)
    mid = slice(60, -60)                                             # away from the clip's ends
    assert np.abs(acc[mid] - expected[mid]).max() < 0.1 * 0.05 * (2 * np.pi) ** 2


def test_belly_and_chest_first_modes_lie_in_2_to_15_hz(body):
    from simgen.softtissue import REGIONS, flesh_mesh
    from simgen.softtissue.modes import region_modes

    mesh = flesh_mesh(body)
    model = FleshModel.for_body(mesh, body, np.zeros((1, body.num_betas)), device="cpu")
    node_region = np.zeros(mesh.num_nodes, dtype=int)
    node_region[mesh.tets.ravel()] = np.repeat(mesh.region, 4)
    modes = region_modes(FleshSolver(model), {r: node_region == REGIONS.index(r) for r in ("belly", "chest")},
                         count=150, share=0.3)
    assert 2.0 <= modes["belly"] <= 15.0 and 2.0 <= modes["chest"] <= 15.0, modes


def test_the_bundled_mesh_carries_the_body_to_its_shapes(body):
    from simgen.softtissue import flesh_mesh

    mesh = flesh_mesh(body)
    skin = np.einsum("vkc,vk->vc", mesh.nodes[mesh.tets[mesh.skin_tet]], mesh.skin_bary)
    err = np.linalg.norm(skin - body.v_template, axis=1)
    assert np.percentile(err, 99) < 0.005 and err.max() < 0.01
    np.testing.assert_allclose(mesh.weights.sum(axis=1), 1.0, atol=1e-5)
    for k in range(4):
        for v in (-2.0, 2.0):
            beta = np.zeros(mesh.shapedirs.shape[2])
            beta[k] = v
            _, vol = rest_shape(mesh.nodes + mesh.shapedirs @ beta, mesh.tets)
            assert np.sum(vol <= 0) <= 1e-3 * mesh.num_tets, (k, v)
    # Its skin follows the body's own shape blend shapes.
    beta = np.zeros(mesh.shapedirs.shape[2])
    beta[2] = 2.0
    moved = mesh.skin((mesh.shapedirs @ beta)[None])[0]
    ref = body.shaped_vertices(beta[None])[0] - body.v_template
    assert np.percentile(np.linalg.norm(moved - ref, axis=1), 95) < 0.1 * np.linalg.norm(ref, axis=1).max()


def test_flesh_mesh_is_built_saved_and_checked(body, tmp_path, monkeypatch):
    from simgen.softtissue import build_flesh_mesh, flesh_mesh
    from simgen.softtissue.mesh import FleshMesh

    monkeypatch.chdir(tmp_path)
    mesh = build_flesh_mesh(body, edge=0.08)
    assert list(tmp_path.iterdir()) == []          # fTetWild's scratch file stays out of the working folder
    _, vol = rest_shape(mesh.nodes, mesh.tets)
    assert np.all(vol > 0) and mesh.boundary.sum() > 100 and (~mesh.boundary).sum() > 0
    assert mesh.skin_tet.shape == (body.num_vertices,) and np.all(mesh.skin_bary >= 0)
    path = mesh.save(tmp_path / "m.npz")
    again = flesh_mesh(body, path)
    np.testing.assert_allclose(again.nodes, mesh.nodes, atol=1e-6)
    assert again.num_tets == mesh.num_tets
    other = FleshMesh(**{**again.__dict__, "body_hash": "0" * 64})
    other.save(tmp_path / "other.npz")
    with pytest.raises(InputError, match="another body model"):
        flesh_mesh(body, tmp_path / "other.npz")
    (tmp_path / "bad.npz").write_bytes(b"not a zip")
    with pytest.raises(InputError, match="bad.npz"):
        flesh_mesh(body, tmp_path / "bad.npz")
    (tmp_path / "cut.npz").write_bytes(path.read_bytes()[: path.stat().st_size // 2])
    with pytest.raises(InputError, match="cut.npz"):
        flesh_mesh(body, tmp_path / "cut.npz")
    with pytest.raises(InputError, match="below half the rate"):
        FleshParams(lowpass=130.0)
