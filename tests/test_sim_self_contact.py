"""Cloth self-contact (vertex-triangle and edge-edge repulsion): finite differences, the analytic energy, and
a sheet falling onto a pinned sheet of the same instance (stopped) and of another instance (not)."""

import numpy as np
import pytest
import warp as wp

from simgen.errors import InputError
from simgen.sim import ClothModel, ClothModelBuilder, ImplicitSolver, SolverConfig
from simgen.sim.energies import SelfContactParams, SelfContactSet, eval_self_contact
from test_sim_energies import energy_of, evaluate, fd_gradient, fd_hessian, gradient_of, grid, rel_err

PARAMS = SelfContactParams(thickness=2.0e-3, stiffness=1.0e4, power=3.0, search_radius=1.0e-2)


def two_triangles(p):
    """Triangle A in the y = 0 plane and triangle B standing up, with its first vertex at p."""
    v = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 0.1], [0.1, 0.0, 0.0],
                  p, [p[0], 0.08, p[2]], [p[0] + 0.05, 0.08, p[2]]], dtype=np.float64)
    return v, np.array([[0, 1, 2], [3, 4, 5]])


@pytest.mark.parametrize("p, expected_d, pairs", [
    ((0.03, 1.0e-3, 0.03), 1.0e-3, 1),                                  # over A's interior
    # Beyond A's hypotenuse edge: the tip against A, and B's two edges from the tip against that
    # edge, all three at the same distance (a vertex-edge contact counts once per pair).
    ((0.0505, 1.0e-3, 0.0505), float(np.sqrt(2 * 0.0005 ** 2 + 1.0e-6)), 3),
])
def test_self_contact_energy_gradient_fd_and_psd_vertex_block(p, expected_d, pairs):
    v, f = two_triangles(p)
    model = ClothModel.from_mesh(v, f, "cotton", device="cpu", dtype=wp.float64)
    cset = SelfContactSet(model, PARAMS)
    cset.update(wp.array(v, dtype=wp.vec3d, device="cpu"))
    assert cset.count.numpy().tolist() == [0, 0, 0, 1, 0, 0]  # only B's tip sees A, never its own triangle

    e, g, h = evaluate(model, eval_self_contact, v, cset)
    assert cset.edge_count.numpy().sum() == pairs - 1
    assert e.sum() == pytest.approx(pairs * 1.0e4 * (2.0e-3 - expected_d) ** 3, rel=1e-9)
    assert rel_err(g, fd_gradient(energy_of(model, eval_self_contact, cset), v)) < 1e-6
    # Momentum: the repulsion is internal, so its forces sum to zero.
    assert np.abs(g.sum(axis=0)).max() < 1e-12 * np.abs(g).max()
    fd_h = fd_hessian(gradient_of(model, eval_self_contact, cset), v)
    if p[0] + p[2] < 0.1:
        # Over the face interior, d is linear in p: the vertex's own block is exact.
        assert rel_err(h[9:12, 9:12], fd_h[9:12, 9:12]) < 1e-6
    # Only diagonal blocks, each PSD.
    for i in range(6):
        for j in range(6):
            block = h[3 * i:3 * i + 3, 3 * j:3 * j + 3]
            if i != j:
                assert not block.any()
            else:
                assert np.linalg.eigvalsh(0.5 * (block + block.T)).min() > -1e-12 * max(np.abs(block).max(), 1.0)
    # Beyond the thickness nothing acts.
    far = v.copy()
    far[3, 1] = 3.0e-3
    e_far, g_far, h_far = evaluate(model, eval_self_contact, far, cset)
    assert e_far.sum() == 0.0 and not g_far.any() and not h_far.any()


def test_edge_edge_repulsion_of_crossing_edges():
    # Triangle A in the y = 0 plane with its long edge along x; triangle B above it with its lower
    # edge along z, 1 mm above A, passing over two of A's edges: no vertex is near a triangle, only
    # edges are close. Exact energy, finite-difference gradient, momentum, PSD blocks.
    v = np.array([[-0.05, 0.0, 0.0], [0.05, 0.0, 0.0], [0.0, 0.0, -0.06],
                  [0.01, 1.0e-3, 0.08], [0.01, 1.0e-3, -0.08], [0.01, 0.06, 0.0]])
    f = np.array([[0, 1, 2], [3, 4, 5]])
    model = ClothModel.from_mesh(v, f, "cotton", device="cpu", dtype=wp.float64)
    cset = SelfContactSet(model, PARAMS)
    cset.update(wp.array(v, dtype=wp.vec3d, device="cpu"))
    assert cset.count.numpy().sum() == 0 and cset.edge_count.numpy().sum() == 2
    e, g, h = evaluate(model, eval_self_contact, v, cset)
    assert e.sum() == pytest.approx(2 * 1.0e4 * (2.0e-3 - 1.0e-3) ** 3, rel=1e-9)
    assert rel_err(g, fd_gradient(energy_of(model, eval_self_contact, cset), v)) < 1e-6
    assert np.abs(g.sum(axis=0)).max() < 1e-12 * np.abs(g).max()
    assert g[3, 1] < 0.0 and g[0, 1] > 0.0  # dE/dx: pushes B's edge up and A's edge down
    for i in range(6):
        block = h[3 * i:3 * i + 3, 3 * i:3 * i + 3]
        assert np.linalg.eigvalsh(0.5 * (block + block.T)).min() > -1e-12 * max(np.abs(block).max(), 1.0)


def stacked_sheets(gap):
    """A pinned 0.12 m sheet at y = 0 and a free 0.06 m sheet gap [m] above its centre."""
    lower_v, lower_f = grid(7, 0.12)
    upper_v, upper_f = grid(4, 0.06)
    upper_v = upper_v + np.array([0.03 + 0.004, gap, 0.03 + 0.007])  # off the lower grid's vertices
    return (lower_v, lower_f), (upper_v, upper_f)


def drop(model, config, steps=60, h=1.0 / 300.0):
    solver = ImplicitSolver(model, config)
    state = model.state()
    for _ in range(steps):
        solver.step(state, state, None, h)
    return state.positions.numpy(), solver.stats


def test_falling_sheet_rests_on_pinned_sheet_of_its_own_instance_only():
    (lv, lf), (uv, uf) = stacked_sheets(gap=4.0e-3)
    n_low = len(lv)
    contact = SolverConfig(self_contact=PARAMS, friction=None, floor=None)

    one = ClothModel.from_mesh(np.vstack([lv, uv]), np.vstack([lf, uf + n_low]), "cotton", device="cpu",
                               pinned=np.arange(n_low))
    x, stats = drop(one, contact)
    upper_y = x[n_low:, 1]
    assert np.isfinite(x).all() and stats["retries"] == 0
    # Rests on the lower sheet: above it, within the repulsion thickness plus a little sag.
    assert upper_y.min() > 0.0
    assert upper_y.max() < PARAMS.thickness + 1.0e-3

    x_off, _ = drop(one, SolverConfig(friction=None, floor=None))
    assert x_off[n_low:, 1].max() < -0.01  # without self-contact it falls through

    builder = ClothModelBuilder()
    builder.add_instance(lv, lf, "cotton", pinned=np.arange(n_low))
    builder.add_instance(uv, uf, "cotton")
    two = builder.finalize("cpu")
    x_two, _ = drop(two, contact)
    assert x_two[n_low:, 1].max() < -0.01  # instances never see each other


def test_self_contact_params_validation():
    with pytest.raises(InputError, match="thickness"):
        SelfContactParams(thickness=0.0)
    with pytest.raises(InputError, match="search_radius"):
        SelfContactParams(thickness=0.02, search_radius=0.01)
    with pytest.raises(InputError, match="max_candidates"):
        SelfContactParams(max_candidates=0)
    with pytest.raises(InputError, match="power"):
        SelfContactParams(power=1.5)
