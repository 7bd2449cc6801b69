"""simulate() (simgen.sim.driver): the T-shirt (1k triangles) on the open body through the start
protocol (relax, shape + pose ramp, rest) and a few frames of a walk, checked against references
that the driver does not compute itself: the numpy BodyModel forward pass (where the body must be)
and a winding-number signed distance (simgen.body.project_to_surface, not the solver's query).

Tiny on purpose (2 + 3 + 2 protocol frames, 4 output frames, 4 substeps): ~5 s on a 2-core CPU.
"""

import json
import os

import numpy as np
import pytest
import warp as wp

from simgen import body as body_pkg
from simgen.body import project_to_surface
from simgen.garment.library import load_garment
from simgen.motion.library import load_motion
from simgen.motion.ops import trim
from simgen.sim import FRAME_STAT_KEYS, SimulationConfig, SimulationResult, simulate
from simgen.errors import InputError

wp.config.quiet = True
DEVICE = os.environ.get("SIMGEN_TEST_DEVICE", "cpu")  # the device machine runs these on "cuda:0"

# beta 2 = +2 widens the open body's torso: 248 of the T-shirt's 527 template vertices (up to
# 1.9 cm deep) lie inside that shaped body in rest pose, so the ramp has real work to do.
BETAS = np.array([0.0, 0.0, 2.0])
FRAMES = 4


@pytest.fixture(scope="module")
def setup():
    body = body_pkg.load("open")
    garment = load_garment("tshirt_1k", body=body)
    # Mid-walk at full speed: the pelvis moves ~13 cm over the 4 output frames.
    clip = trim(load_motion("walk"), 2.0, 2.5)
    cfg = SimulationConfig(substeps=4, relax_frames=2, ramp_frames=3, rest_frames=2, record_body=True, device=DEVICE)
    result = simulate(garment, body, clip, BETAS, cfg, frames=FRAMES)
    return body, garment, clip, result


def signed_distance(points, body_vertices, body):
    return project_to_surface(points, body_vertices, body.faces).signed_distance


def test_shapes_and_finite(setup):
    body, garment, clip, r = setup
    V = garment.num_vertices
    assert isinstance(r, SimulationResult)
    assert r.positions.shape == (FRAMES, V, 3) and r.positions.dtype == np.float32
    assert np.all(np.isfinite(r.positions))
    assert r.protocol_positions.shape == (2 + 3 + 2, V, 3)
    assert list(r.protocol_phases) == ["relax"] * 2 + ["ramp"] * 3 + ["rest"] * 2
    assert r.body_vertices.shape == (FRAMES, body.num_vertices, 3)
    assert r.dt == pytest.approx(1.0 / 30.0 / 4)
    for k in FRAME_STAT_KEYS:
        assert r.stats[k].shape == (FRAMES,), k
        assert np.all(np.isfinite(r.stats[k])), k
    # Every animated frame but the first (the protocol's end state) took solver steps.
    assert np.all(r.stats["newton_iterations"][1:] >= 4) and np.all(r.stats["cg_iterations"][1:] > 0)
    assert np.all(r.stats["wall_time"] > 0)


def test_body_is_the_shaped_posed_body(setup):
    """The ramp reaches the target shape and the clip's pose: the driver's posed body equals the
    numpy forward pass with the betas at each output frame."""
    body, garment, clip, r = setup
    ref = body.forward(np.repeat(body.check_betas(BETAS), FRAMES, 0), clip.poses[:FRAMES], clip.trans[:FRAMES])
    assert np.max(np.abs(r.body_vertices - ref.vertices)) < 1e-4


def test_no_vertex_inside_except_self_intersections(setup):
    body, garment, clip, r = setup
    # The template garment would be inside the shaped body: the check below is not vacuous.
    rest_shaped = body.forward(body.check_betas(BETAS), np.zeros((1, 24, 3)), clip.trans[:1]).vertices[0]
    assert np.sum(signed_distance(garment.vertices + clip.trans[0], rest_shaped, body) < -1e-3) > 50
    for k in range(FRAMES):
        sd = signed_distance(r.positions[k], r.body_vertices[k], body)
        deep = int(np.sum(sd < -1e-3))
        assert deep <= r.stats["self_intersection_count"][k], (k, deep, sd.min())
        assert r.stats["max_depth_regular"][k] <= 1e-3
        # The driver's own inside count (winding number) agrees with the independent query.
        assert abs(int(np.sum(sd < 0.0)) - r.stats["inside_count"][k]) <= 2
    # At the first clip frame the shaped body is reached and the garment is outside it, except
    # where the arms hanging at the widened torso overlap it (the counted self-intersections).
    assert r.stats["self_intersection_count"][0] < 0.2 * garment.num_vertices


def test_placement_statistics_equal_the_host_measures(setup):
    """The driver's on-the-body measures (the garment skinned on the device by the body's LBS kernel,
    the winding-number query's distances) equal simgen.sim.placement's on the numpy forward pass,
    numpy LBS and the independent surface query."""
    from simgen.garment.skinning import lbs
    from simgen.sim.placement import PLACEMENT_KEYS, garment_reference, placement_row

    body, garment, clip, r = setup
    betas = np.repeat(body.check_betas(BETAS), FRAMES, 0)
    posed = body.forward(betas, clip.poses[:FRAMES], clip.trans[:FRAMES])
    ref = garment_reference(garment, body)
    rest = ref.rest_vertices(garment.vertices, betas)
    x_lbs = lbs(rest, garment.skin_weights, posed.transforms)
    up = lbs(rest + [0.0, 1.0, 0.0], garment.skin_weights, posed.transforms) - x_lbs
    assert 0 < ref.support.sum() < garment.num_vertices
    for k in range(FRAMES):
        dist = np.abs(signed_distance(r.positions[k], posed.vertices[k], body))
        host = placement_row(r.positions[k], x_lbs[k], up[k], dist, ref.support)
        for key in PLACEMENT_KEYS:
            tol = 2.0 / garment.num_vertices if key == "body_share" else 2e-4
            assert r.stats[key][k] == pytest.approx(host[key], abs=tol), (k, key)
    assert np.all(r.stats["support_drop"] < 0.05) and np.all(r.stats["body_share"] > 0.5)


def test_garment_follows_the_body(setup):
    body, garment, clip, r = setup
    joints = body.forward(np.repeat(body.check_betas(BETAS), FRAMES, 0), clip.poses[:FRAMES],
                          clip.trans[:FRAMES]).joints
    pelvis = joints[:, 0] - joints[0, 0]
    assert np.linalg.norm(pelvis[-1]) > 0.1  # the body really moves
    centroid = r.positions.mean(axis=1) - r.positions[0].mean(axis=0)
    np.testing.assert_allclose(centroid, pelvis, atol=0.03)


def test_save_npz_round_trip(setup, tmp_path):
    _, garment, _, r = setup
    path = r.save_npz(tmp_path / "run.npz")
    with np.load(path) as z:
        np.testing.assert_array_equal(z["positions"], r.positions)
        np.testing.assert_array_equal(z["faces"], garment.faces)
        assert float(z["fps"]) == 30.0
        np.testing.assert_array_equal(z["stats_max_depth"], r.stats["max_depth"])
        meta = json.loads(str(z["metadata"]))
    assert meta["garment"] == "tshirt_1k" and meta["betas"][2] == 2.0 and meta["frames"] == FRAMES


def test_config_validation():
    with pytest.raises(InputError):
        SimulationConfig(ramp_frames=0)
    with pytest.raises(InputError):
        SimulationConfig(substeps=0)
    with pytest.raises(InputError):
        SimulationConfig(material_overrides={"not_a_field": 1.0}).resolve_material()
    assert SimulationConfig(material="denim", material_overrides={"area_density": 0.5}).resolve_material().area_density == 0.5


@pytest.mark.parametrize("impact_rounds", [4, 0])
def test_self_contact_run_ends_every_frame_untangled(impact_rounds):
    """The same run with self-contact on (repulsion, the impact filter or none, frame-end
    untangling): finite, and no recorded frame has a crossing edge."""
    from dataclasses import replace

    from simgen.params import SelfContactParams

    body = body_pkg.load("open")
    garment = load_garment("tshirt_1k", body=body)
    clip = trim(load_motion("walk"), 2.0, 2.5)
    cfg = SimulationConfig(substeps=4, relax_frames=2, ramp_frames=3, rest_frames=2, device=DEVICE)
    cfg = replace(cfg, solver=replace(cfg.solver, self_contact=SelfContactParams(impact_rounds=impact_rounds)))
    result = simulate(garment, body, clip, BETAS, cfg, frames=FRAMES)
    assert np.all(np.isfinite(result.positions))
    assert np.all(result.stats["crossing_edges"] == 0) and np.all(result.protocol_stats["crossing_edges"] == 0)
