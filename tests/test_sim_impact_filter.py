"""The impact filter (continuous collision detection after every substep, rigid impact zones):
exact times of impact of crossing and passing primitives, impacting pairs moving as one body with
their momentum, and cloth that an unprotected step tangles (a sheet thrown through a pinned one, a
sleeve squashed through itself) ending untangled, while instances that overlap in space and layers
sliding past each other are left alone."""

import numpy as np
import pytest
import warp as wp

from simgen.errors import InputError
from simgen.garment.crossings import count_crossing_edges
from simgen.params import SelfContactParams
from simgen.sim import BodyCollider, ClothModel, ClothModelBuilder, ImplicitSolver, SolverConfig
from simgen.sim.impact_filter import ImpactFilter, impact_kernels
from test_sim_energies import box_body, grid

H = 1.0 / 300.0
SELF = SelfContactParams()


_time_of_impact = impact_kernels(wp.float64).time_of_impact


@wp.kernel
def _toi(kind: int, x: wp.array(dtype=wp.vec3d), dx: wp.array(dtype=wp.vec3d), out: wp.array(dtype=wp.float64)):
    out[0] = _time_of_impact(kind, x[0], x[1], x[2], x[3], dx[0], dx[1], dx[2], dx[3])


def toi(kind, x, dx):
    out = wp.zeros(1, dtype=wp.float64, device="cpu")
    wp.launch(_toi, dim=1, device="cpu", inputs=[kind, wp.array(np.asarray(x, float), dtype=wp.vec3d, device="cpu"),
                                                  wp.array(np.asarray(dx, float), dtype=wp.vec3d, device="cpu"), out])
    return float(out.numpy()[0])


TRIANGLE = [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]


def test_point_through_triangle_stops_before_the_plane():
    # The point falls from y = 0.1 to y = -0.1 through the triangle's interior: it reaches the plane
    # at t = 0.5; additive CCD returns a time before it, with at least 10% of the gap left.
    x = [[0.2, 0.1, 0.2]] + TRIANGLE
    dx = [[0.0, -0.2, 0.0]] + [[0.0, 0.0, 0.0]] * 3
    t = toi(0, x, dx)
    assert 0.4 < t < 0.5
    assert 0.1 - 0.2 * t >= 0.1 * 0.1 * 0.99


def test_a_pair_that_closes_but_ends_apart_has_no_impact():
    # A point 3 mm over the triangle slides 2 mm sideways and ends 0.6 mm over it: closer, but not
    # within 10% of the start distance beyond the 0.1 mm separation (0.39 mm), so no impact. The
    # additive steps must stop at the path's end: a step past it measured the distance on the
    # path's extension and reported an impact at t = 0.84. Ending 0.2 mm over it is one.
    start, still = [[0.2, 3.0e-3, 0.2], *TRIANGLE], [[0.0, 0.0, 0.0]] * 3
    assert toi(0, start, [[2.0e-3, 0.6e-3 - 3.0e-3, 0.0], *still]) == 1.0
    assert toi(0, start, [[2.0e-3, 0.2e-3 - 3.0e-3, 0.0], *still]) < 1.0


def test_point_beside_or_parallel_to_triangle_has_no_impact():
    beside = [[2.0, 0.1, 2.0]] + TRIANGLE                  # passes the plane outside the triangle
    assert toi(0, beside, [[0.0, -0.2, 0.0]] + [[0.0, 0.0, 0.0]] * 3) == 1.0
    above = [[0.2, 0.002, 0.2]] + TRIANGLE                  # slides 1.2 cm, 2 mm above it (3.5 m/s at 300 Hz)
    assert toi(0, above, [[0.01, 0.0, 0.006]] + [[0.0, 0.0, 0.0]] * 3) == 1.0
    together = [[0.2, 0.002, 0.2]] + TRIANGLE               # everything moves as one
    assert toi(0, together, [[0.3, -0.5, 0.1]] * 4) == 1.0


def test_crossing_edges_impact_and_skew_ones_do_not():
    # Edge a along x at y = 0.1 moving down through edge c along z at y = 0: they meet at t = 0.5.
    x = [[-1.0, 0.1, 0.0], [1.0, 0.1, 0.0], [0.0, 0.0, -1.0], [0.0, 0.0, 1.0]]
    down = [[0.0, -0.2, 0.0]] * 2 + [[0.0, 0.0, 0.0]] * 2
    assert 0.4 < toi(1, x, down) < 0.5
    shifted = [[-1.0, 0.1, 2.0], [1.0, 0.1, 2.0], [0.0, 0.0, -1.0], [0.0, 0.0, 1.0]]  # passes beyond c's end
    assert toi(1, shifted, down) == 1.0


def test_an_edge_through_an_edge_is_stopped():
    # Triangle A is a sliver along x (its far corner 1 mm off the edge); B's lower edge, along z
    # and 5 cm above, is carried 10 cm down through A's long edge. No vertex ever passes through a
    # triangle (B's corners stay outside A, A's outside B): only the edge-edge test can stop it.
    v = np.array([[-1.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.3, 0.0, -1.0e-3],
                  [0.0, 0.05, 0.5], [0.0, 0.05, -0.5], [0.0, 0.3, 0.0]])
    f = np.array([[0, 1, 2], [3, 4, 5]])
    model = ClothModel.from_mesh(v, f, "cotton", device="cpu")
    x1 = v.copy()
    x1[3:, 1] -= 0.1
    state = model.state()
    state.positions.assign(x1.astype(np.float32))
    filt = ImpactFilter(model)
    x0 = wp.array(v.astype(np.float32), dtype=wp.vec3, device="cpu")
    assert count_crossing_edges(x1, f)[0] > 0  # unfiltered, B's edge ends through A
    filt.apply(x0, state)
    x = state.positions.numpy()
    assert count_crossing_edges(x, f)[0] == 0
    # A and the edge of B became one zone: they translate by their mass-weighted mean motion
    # (momentum kept); B's far corner, in no impacting pair, keeps its own.
    zone = [0, 1, 2, 3, 4]
    mass = model.vertex_mass.numpy()[zone, None]
    mean = (mass * (x1 - v)[zone]).sum(axis=0) / mass.sum()
    assert np.allclose((x - v)[zone], mean, atol=1e-6) and -0.1 < mean[1] < 0.0
    assert np.allclose(x[5], x1[5])


def thrown_sheet(speed):
    """A pinned 0.12 m sheet at y = 0 and a 0.06 m sheet 1.5 cm above it thrown down at speed [m/s]."""
    lv, lf = grid(7, 0.12)
    uv, uf = grid(4, 0.06)
    uv = uv + np.array([0.034, 0.015, 0.037])
    return np.vstack([lv, uv]), np.vstack([lf, uf + len(lv)]), len(lv)


def run(model, config, velocity, steps, body=None):
    solver = ImplicitSolver(model, config)
    state = model.state()
    state.velocities.assign(np.asarray(velocity, dtype=np.float32))
    frames = []
    for _ in range(steps):
        solver.step(state, state, body, H)
        frames.append(state.positions.numpy().astype(np.float64))
    return np.array(frames), solver


@pytest.mark.parametrize("self_contact, tangles", [(None, True), (SELF, False)])
def test_sheet_thrown_through_a_pinned_sheet(self_contact, tangles):
    v, f, n_low = thrown_sheet(speed=8.0)
    model = ClothModel.from_mesh(v, f, "cotton", device="cpu", pinned=np.arange(n_low))
    vel = np.zeros_like(v)
    vel[n_low:, 1] = -8.0  # 2.7 cm per step: through the lower sheet in one step without the filter
    frames, solver = run(model, SolverConfig(self_contact=self_contact, friction=None, floor=None), vel, steps=6)
    crossings = count_crossing_edges(frames, f)
    upper_y = frames[:, n_low:, 1]
    if tangles:
        assert crossings.max() > 0 or upper_y[-1].max() < 0.0
    else:
        assert crossings.max() == 0
        assert upper_y.min() > 0.0  # still above the pinned sheet (which stays at y = 0)


def test_projection_marks_the_vertices_touching_the_body():
    # Four cloth vertices over a box's top face (y = 0) at heights -1, +1, +5 and +1.5 mm: the
    # projection marks those inside or within the touch distance, and only those (before it moves them).
    _, box_v, box_f = box_body(center=(0.0, -0.125, 0.0))
    body = BodyCollider.from_static(box_v, box_f, device="cpu")
    v = np.array([[0.01, -1.0e-3, 0.02], [0.04, 1.0e-3, 0.02], [0.01, 5.0e-3, 0.05], [0.04, 1.5e-3, 0.05]])
    model = ClothModel.from_mesh(v, [[0, 1, 2], [1, 3, 2]], "cotton", device="cpu")
    for distance, expected in ((2.0e-3, [1, 1, 0, 1]), (1.2e-3, [1, 1, 0, 0])):
        state = model.state()
        touching = wp.zeros(4, dtype=wp.int32, device="cpu")
        normal = wp.zeros(4, dtype=wp.vec3, device="cpu")
        plane = wp.zeros(4, dtype=wp.float32, device="cpu")
        body.project(model, state, offset=2.0e-4, touching=touching, touch_distance=distance, touch_normal=normal,
                     touch_plane=plane)
        assert touching.numpy().tolist() == expected
        marked = np.flatnonzero(expected)
        # Their half-spaces: the face's outward normal, and y >= the face plus the offset.
        assert np.allclose(normal.numpy()[marked], [0.0, 1.0, 0.0], atol=1e-6)
        assert np.allclose(plane.numpy()[marked], 2.0e-4, atol=1e-6)
        assert state.positions.numpy()[0, 1] == pytest.approx(2.0e-4, abs=1e-6)  # the inside one: on the face + offset
    with pytest.raises(InputError, match="touching, touch_normal and touch_plane together"):
        body.project(model, model.state(), touching=touching)


def sheets_on_box(lower, upper):
    """thrown_sheet's two sheets, free, at heights lower and upper [m] over a box whose top face is
    y = 0: vertices, faces, the lower sheet's vertex count, the cloth model and the box's collider."""
    v, f, n_low = thrown_sheet(speed=0.0)
    v[:n_low, 1] = lower
    v[n_low:, 1] = upper
    _, box_v, box_f = box_body(center=(0.06, -0.125, 0.06))
    body = BodyCollider.from_static(box_v, box_f, device="cpu")
    return v, f, n_low, ClothModel.from_mesh(v, f, "cotton", device="cpu"), body


def test_sheet_thrown_onto_a_sheet_lying_on_the_body():
    # The lower sheet lies free 1 mm above a box (inside the contact margin); the upper one, 4 mm
    # above it, is thrown down at 20 m/s (6.7 cm per step). Their impacts join them in zones, but
    # the lower sheet touches the body, so the zones follow it and keep it out of the box (the
    # zones' mass-weighted mean carried it 17 mm into the box before), and the upper sheet stops on it.
    v, f, n_low, model, body = sheets_on_box(1.0e-3, 5.0e-3)
    vel = np.zeros_like(v)
    vel[n_low:, 1] = -20.0
    frames, _ = run(model, SolverConfig(self_contact=SELF, friction=None, floor=None), vel, steps=3, body=body)
    assert count_crossing_edges(frames, f).max() == 0
    for x in frames:
        depth, _ = body.penetration(model, wp.array(x.astype(np.float32), dtype=wp.vec3, device="cpu"))
        assert depth[0] == 0.0
        assert x[n_low:, 1].min() > x[:n_low, 1].max() + 1.0e-3


def test_box_rising_through_two_layers_carries_both_out():
    # Two free sheets 1 and 4 mm above a box; the box rises 1 cm per step (3 m/s), through both in
    # each step. The projection puts both on its face and their paths cross: one zone, all its
    # members touching. Its translation must keep each of them outside (their body half-spaces),
    # so both leave the box with the 3 mm between them kept, and nothing crosses.
    v, f, n_low, model, body = sheets_on_box(1.0e-3, 4.0e-3)
    box_v = body.points.numpy().astype(np.float64)
    solver = ImplicitSolver(model, SolverConfig(self_contact=SELF, friction=None, floor=None))
    state = model.state()
    for k in range(3):
        body.update(box_v + [0.0, 0.01 * (k + 1), 0.0], dt=H)
        solver.step(state, state, body, H)
        x = state.positions.numpy().astype(np.float64)
        depth, _ = body.penetration(model, state.positions)
        assert depth[0] == 0.0
        assert count_crossing_edges(x, f)[0] == 0
        assert x[n_low:, 1].min() - x[:n_low, 1].max() > 2.5e-3


def tube(n_around=12, n_along=6, radius=0.03, length=0.1):
    """An open cylinder along x (a sleeve), (V, 3) and (F, 3)."""
    a = np.linspace(0.0, 2 * np.pi, n_around, endpoint=False)
    xs = np.linspace(0.0, length, n_along)
    v = np.array([[x, radius * np.cos(t), radius * np.sin(t)] for x in xs for t in a])
    f = []
    for i in range(n_along - 1):
        for j in range(n_around):
            p, q = i * n_around + j, i * n_around + (j + 1) % n_around
            f += [[p, q, q + n_around], [p, q + n_around, p + n_around]]
    return v, np.array(f)


@pytest.mark.parametrize("self_contact, tangles", [(None, True), (SELF, False)])
def test_sleeve_squashed_through_itself(self_contact, tangles):
    v, f = tube(n_around=16)
    v[:, 1] *= 0.004 / 0.03  # a sleeve lying flat: its layers 8 mm apart
    model = ClothModel.from_mesh(v, f, "cotton", device="cpu")
    vel = np.zeros_like(v)
    vel[v[:, 1] > 1.0e-4, 1] = -10.0  # the upper layer pressed onto the lower one: 3.3 cm per step
    config = SolverConfig(self_contact=self_contact, friction=None, floor=None)
    frames, _ = run(model, config, vel, steps=4)
    crossings = count_crossing_edges(frames, f)
    assert (crossings.max() > 0) == tangles


def test_overlapping_instances_and_sliding_layers_are_left_alone():
    # Two copies of the same sheets: in copy 0 the upper sheet slides 2 mm above the lower one (no
    # impact), in copy 1 it is thrown through copy 0's space with no sheet of its own below it.
    v, f, n_low = thrown_sheet(speed=0.0)
    v_slide = v.copy()
    v_slide[n_low:, 1] = 2.5e-3
    b = ClothModelBuilder()
    b.add_instance(v_slide, f, "cotton", pinned=np.arange(n_low))
    b.add_instance(v[n_low:], f[f.min(axis=1) >= n_low] - n_low, "cotton")
    model = b.finalize("cpu")
    vel = np.zeros((model.num_vertices, 3))
    vel[n_low:len(v), 0] = 3.0            # sliding sideways in copy 0
    vel[len(v):, 1] = -8.0                # thrown down through where copy 0's sheets are
    frames, solver = run(model, SolverConfig(self_contact=SELF, friction=None, floor=None), vel,
                         steps=3)
    assert solver.impact_filter.impacts.numpy().tolist() == [0, 0]
    assert frames[-1, len(v):, 1].max() < -0.05  # copy 1 went straight through copy 0's space
    assert frames[-1, n_low:len(v), 0].min() > v[n_low:, 0].min() + 0.02  # copy 0 slid freely
