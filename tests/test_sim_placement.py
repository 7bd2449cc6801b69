"""What keeps garments on the body and what tells when they are not: the waistband tied to the
body (simgen.garment.waistband, simgen.sim.energies.attachment), the floor
(simgen.sim.energies.floor) and the placement measures (simgen.sim.placement).

References nobody here chose: a rigid motion of the body carries a tied band rigidly; the springs
of a hanging tube carry its weight, so the band sags by exactly the recipe's sag; a cloth resting
on the floor sits where the penalty force equals each vertex's weight; a garment translated down
the body or off it, and a dress whose skirt flares out, against the limits of the check. CPU,
small meshes: ~20 s.
"""

import math
import os
from types import SimpleNamespace

import numpy as np
import pytest
import warp as wp

from simgen import body as body_pkg
from simgen.errors import InputError
from simgen.garment.garment import Garment
from simgen.garment.library import load_garment
from simgen.garment.skinning import lbs
from simgen.garment.waistband import band_vertices
from simgen.sim import BodyCollider, ClothModel, ImplicitSolver, SolverConfig
from simgen.sim.energies import ContactParams, GravityParams
from simgen.sim.placement import (MIN_BODY_SHARE, garment_reference, placement_problems,
                                  placement_row)

wp.config.quiet = True
DEVICE = os.environ.get("SIMGEN_TEST_DEVICE", "cpu")


# -- an elastic ring (and a tube hanging from it) on a vertical cylinder ------------------------------

def tube(radius, y_top, height, n_around, n_rows):
    """A vertical open tube of quads split in two, rows from y_top downwards; returns (V, 3), (F, 3)."""
    angles = np.arange(n_around) * 2 * np.pi / n_around
    ys = y_top - np.linspace(0.0, height, n_rows)
    v = np.array([[radius * np.cos(a), y, radius * np.sin(a)] for y in ys for a in angles])
    f = []
    for r in range(n_rows - 1):
        for i in range(n_around):
            a, b = r * n_around + i, r * n_around + (i + 1) % n_around
            c, d = a + n_around, b + n_around
            f += [[a, c, d], [a, d, b]]  # counter-clockwise seen from outside
    return v, np.array(f)


def band_garment(v, f, n_around, width=0.03, sag=1e-3):
    """A Garment whose top loop (the first n_around vertices) is a waist opening with a waistband."""
    meta = {"openings": [{"name": "waist", "centroid_m": v[:n_around].mean(axis=0).tolist()}],
            "waistband": {"opening": "waist", "width_m": width, "sag_m": sag}}
    weights = np.zeros((len(v), 24))
    weights[:, 0] = 1.0
    return Garment("tube", v, f, weights, meta)


def cylinder_model(radius, n=96):
    """The rigid cylinder as a stand-in body model (what the waistband needs of one: v_template, faces)."""
    import trimesh

    cyl = trimesh.creation.cylinder(radius=radius, segment=[[0, -1.0, 0], [0, 1.0, 0]], sections=n)
    return SimpleNamespace(name="cylinder", v_template=np.asarray(cyl.vertices), faces=np.asarray(cyl.faces))


def test_waistband_is_the_cloth_along_the_waist_opening():
    """The band: every vertex within width_m of the waist loop along the mesh (so within width_m
    in space), the loop included; garments worn from the shoulders have none."""
    from simgen.garment.mesh import boundary_loops

    g = load_garment("pants")
    band = band_vertices(g)
    width = g.metadata["waistband"]["width_m"]
    loop = max(boundary_loops(g.faces), key=lambda lp: g.vertices[lp, 1].mean())
    assert set(loop.tolist()) <= set(band.tolist())
    gap = np.linalg.norm(g.vertices[band][:, None] - g.vertices[loop][None], axis=2).min(axis=1)
    assert gap.max() <= width + 1e-9
    near = np.linalg.norm(g.vertices[:, None] - g.vertices[loop][None], axis=2).min(axis=1) < 0.5 * width
    assert near.sum() <= len(band) and set(np.flatnonzero(near)) <= set(band.tolist())
    assert len(band_vertices(load_garment("tshirt_1k"))) == 0 and len(band_vertices(load_garment("dress_1k"))) == 0


def test_waistband_metadata_is_checked():
    v, f = tube(0.1, 0.0, 0.03, 24, 3)
    g = band_garment(v, f, 24, width=1.5)
    with pytest.raises(InputError, match="width_m"):
        band_vertices(g)
    g.metadata["waistband"].update(width_m=0.03, opening="neck")
    with pytest.raises(InputError, match="opening 'neck'"):
        band_vertices(g)
    with pytest.raises(InputError, match="needs the body"):
        ClothModel.from_garment(load_garment("skirt_1k"), device=DEVICE)


def test_attached_band_moves_rigidly_with_the_body():
    """Tied to a cylinder that then turns 40 degrees about its axis and rises 5 cm, the band (no
    gravity, relaxed) ends where the same rigid motion takes its rest positions: each tie's point
    and offset are carried by its body triangle."""
    R, n = 0.1, 32
    v, f = tube(R + 0.012, 0.0, 0.05, n, 3)
    g = band_garment(v, f, n, width=0.06)
    body = cylinder_model(R)
    model = ClothModel.from_garment(g, "cotton", body=body, device=DEVICE, dtype=wp.float64)
    assert model.num_attachments == len(v)
    collider = BodyCollider.from_static(body.v_template, body.faces, device=DEVICE)
    c, s_ = math.cos(math.radians(40)), math.sin(math.radians(40))
    turn = np.array([[c, 0, s_], [0, 1, 0], [-s_, 0, c]])
    turned = body.v_template @ turn.T + [0.0, 0.05, 0.0]
    # Turned once, then held there: the solver places the body between its last two poses within a
    # step (a guard retry's half step would see it half-turned).
    collider.update(turned, dt=1.0)
    collider.update(turned, dt=1.0)
    solver = ImplicitSolver(model, SolverConfig(newton_iterations=3, cg_iterations=300, cg_tolerance=1e-12, floor=None,
                                                gravity=GravityParams((0.0, 0.0, 0.0)), friction=None))
    state = model.state()
    for _ in range(40):
        solver.step(state, state, collider, 0.05)
        state.velocities.zero_()
    err = np.abs(state.positions.numpy() - (v @ turn.T + [0.0, 0.05, 0.0])).max()
    print(f"attached band on a turned cylinder: largest distance from the carried rest shape {1e6 * err:.2f} um")
    assert err < 2e-5


def test_a_tube_hanging_from_its_waistband_sags_by_sag_m():
    """A 30 cm cotton tube tied at its top 3 cm to a cylinder, relaxed under gravity (no friction):
    its springs, k = m g / (A sag_m) each, carry its whole weight, so the band sits sag_m lower on
    average (the springs act in parallel; the tube's own stretch does not enter)."""
    R, n, sag = 0.1, 32, 2e-3
    v, f = tube(R + 0.012, 0.0, 0.3, n, 13)
    g = band_garment(v, f, n, width=0.03, sag=sag)
    body = cylinder_model(R)
    model = ClothModel.from_garment(g, "cotton", body=body, device=DEVICE, dtype=wp.float64)
    band = model.host.attach_vertex
    collider = BodyCollider.from_static(body.v_template, body.faces, device=DEVICE)
    solver = ImplicitSolver(model, SolverConfig(newton_iterations=5, cg_iterations=400, cg_tolerance=1e-12, floor=None,
                                                friction=None))
    state = model.state()
    for _ in range(100):
        solver.step(state, state, collider, 0.05)
        state.velocities.zero_()
    drop = v[band, 1].mean() - state.positions.numpy()[band, 1].mean()
    weight = model.host.vertex_mass.sum() * 9.81
    pull = (model.host.attach_stiffness * (v[band, 1] - state.positions.numpy()[band, 1])).sum()
    print(f"hanging tube: band sags {1e3 * drop:.4f} mm (sag_m {1e3 * sag} mm), springs {pull:.5f} N, "
          f"weight {weight:.5f} N")
    assert pull == pytest.approx(weight, rel=1e-4)
    assert drop == pytest.approx(sag, rel=1e-4)


# -- the floor ------------------------------------------------------------------------------------

def test_cloth_rests_on_the_floor_where_the_penalty_carries_its_weight():
    """A square dropped from 5 cm settles on the floor y = 0: each interior vertex where
    k p (margin - y)^(p-1) = m g, i.e. y = margin - sqrt(m g / (3 k)) for p = 3; none below 0."""
    n = 9
    us = np.linspace(-0.1, 0.1, n)
    v = np.array([[a, 0.05, b] for a in us for b in us])
    f = np.array([[i * n + j, i * n + j + 1, (i + 1) * n + j + 1] for i in range(n - 1) for j in range(n - 1)]
                 + [[i * n + j, (i + 1) * n + j + 1, (i + 1) * n + j] for i in range(n - 1) for j in range(n - 1)])
    model = ClothModel.from_mesh(v, f, "cotton", device=DEVICE, dtype=wp.float64)
    contact = ContactParams()
    solver = ImplicitSolver(model, SolverConfig(newton_iterations=3, cg_iterations=200, cg_tolerance=1e-10,
                                                floor=0.0, contact=contact))
    state = model.state()
    lowest = np.inf
    for _ in range(150):
        solver.step(state, state, None, 1.0e-2)
        lowest = min(lowest, state.positions.numpy()[:, 1].min())
    x = state.positions.numpy()
    inner = [i * n + j for i in range(1, n - 1) for j in range(1, n - 1)]
    m = model.host.vertex_mass[inner]
    expected = contact.margin - np.sqrt(m * 9.81 / (3 * contact.stiffness))
    print(f"floor: lowest over the fall {1e3 * lowest:.3f} mm, interior heights {1e3 * x[inner, 1].min():.4f}-"
          f"{1e3 * x[inner, 1].max():.4f} mm, expected {1e3 * expected.mean():.4f} mm")
    assert lowest >= 0.0
    assert np.allclose(x[inner, 1], expected, atol=2e-5)
    assert np.abs(state.velocities.numpy()).max() < 1e-3


def test_floor_projection_lifts_what_a_step_put_below_it():
    v = np.array([[0.0, -0.01, 0.0], [0.1, 0.02, 0.0], [0.0, 0.02, 0.1]])
    model = ClothModel.from_mesh(v, np.array([[0, 1, 2]]), "cotton", device=DEVICE)
    state = model.state()
    state.velocities.assign(np.tile([0.0, -1.0, 0.0], (3, 1)))
    from simgen.sim.energies import project_floor

    project_floor(model, state, 0.0, 2e-4)
    x, vel = state.positions.numpy(), state.velocities.numpy()
    assert x[0, 1] == pytest.approx(2e-4) and vel[0, 1] == 0.0
    assert x[1, 1] == pytest.approx(0.02) and vel[1, 1] == -1.0
    with pytest.raises(InputError, match="floor"):
        SolverConfig(floor=float("nan"))


# -- the measures and their limits ------------------------------------------------------------------

@pytest.fixture(scope="module")
def posed():
    """The open body mid-walk (betas 0) and the LBS positions of pants_1k and dress_1k on it."""
    from simgen.motion.library import load_motion
    from simgen.body import project_to_surface

    body = body_pkg.load("open")
    clip = load_motion("walk")
    out = body.forward(np.zeros((1, body.num_betas)), clip.poses[20:21], clip.trans[20:21])
    res = {}
    for name in ("pants_1k", "dress_1k"):
        g = load_garment(name, body=body)
        ref = garment_reference(g, body)
        rest = ref.rest_vertices(g.vertices, np.zeros((1, body.num_betas)))
        x = lbs(rest, g.skin_weights, out.transforms)[0]
        up = lbs(rest + [0.0, 1.0, 0.0], g.skin_weights, out.transforms)[0] - x

        def measure(points, ref=ref, x=x, up=up):
            dist = np.abs(project_to_surface(points, out.vertices[0], body.faces).signed_distance)
            return placement_row(points, x, up, dist, ref.support)

        res[name] = (x, measure, out.joints[0])
    return res


def problems(row):
    return placement_problems({k: np.array([v]) for k, v in row.items()})


def test_a_worn_garment_passes(posed):
    for name in ("pants_1k", "dress_1k"):
        x, measure, _ = posed[name]
        row = measure(x)
        assert row["support_drop"] == pytest.approx(0.0, abs=1e-9) and row["lbs_offset"] == pytest.approx(0.0, abs=1e-9)
        print(f"{name} worn: {100 * row['body_share']:.0f}% on the body")
        assert row["body_share"] > 0.4 and problems(row) == []


def test_a_waistband_pushed_down_to_the_hips_fails(posed):
    """The pants moved down until their waistband's top is level with the hip joints."""
    x, measure, joints = posed["pants_1k"]
    shift = x[:, 1].max() - joints[[1, 2], 1].mean()
    row = measure(x - [0.0, shift, 0.0])
    assert 0.1 < shift < 0.15 and row["support_drop"] == pytest.approx(shift, abs=0.01)
    assert row["body_share"] > MIN_BODY_SHARE
    assert [p.split(":")[0] for p in problems(row)] == ["the garment slipped"]


def test_a_garment_dropped_from_the_body_fails(posed):
    x, measure, _ = posed["pants_1k"]
    dropped = x.copy()  # in a heap at the feet, a tenth of its height, its lowest point 2 mm under the floor
    dropped[:, 1] = 0.1 * (x[:, 1] - x[:, 1].min()) - 0.002
    row = measure(dropped)
    assert row["support_drop"] > 0.5
    messages = problems(row)
    assert len(messages) == 2 and "slipped" in messages[0] and "below the floor" in messages[1]


def test_a_dress_at_full_swing_passes(posed):
    """The dress's skirt flared out to 60 degrees (a twirl): every vertex below the hips turned
    about the horizontal tangent through the hip line, away from the legs."""
    x, measure, joints = posed["dress_1k"]
    hip_y = joints[[1, 2], 1].mean()
    centre = joints[0] * [1, 0, 1]
    swung = x.copy()
    below = x[:, 1] < hip_y
    radial = (x[below] - centre) * [1, 0, 1]
    radial /= np.linalg.norm(radial, axis=1, keepdims=True)
    length = hip_y - x[below, 1]
    angle = np.deg2rad(60.0)
    swung[below] = x[below] + radial * (length * np.sin(angle))[:, None]
    swung[below, 1] = hip_y - length * np.cos(angle)
    row = measure(swung)
    print(f"dress at full swing: {100 * row['body_share']:.0f}% on the body, support drop "
          f"{100 * row['support_drop']:.2f} cm")
    assert row["body_share"] < 0.8
    assert problems(row) == []


def test_problems_name_the_checked_frame_numbers():
    """A check that measures every 10th frame reports frame numbers, not positions in its list."""
    stats = {"body_share": np.array([0.9, 0.9, 0.1]), "support_drop": np.array([0.0, 0.2, 0.3]),
             "min_height": np.array([0.1, 0.1, -0.01]), "lbs_offset": np.zeros(3)}
    out = placement_problems(stats, 0.0, frames=[0, 10, 20])
    assert [m.split(":")[0] for m in out] == ["the garment slipped", "the garment left the body", "cloth 10.0 mm below the floor on 1 of 3 frames from frame 20"]
    assert "on 2 of 3 frames from frame 10" in out[0] and "from frame 20" in out[1]
    assert placement_problems(stats, None, frames=[0, 10, 20])[-1].startswith("the garment left")
