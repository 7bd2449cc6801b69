"""Garment skinning weights, LBS and inverse LBS, checked against facts none of us chose.

Closest weights are exact on the body surface (they ARE the body's weights at its vertices and the
barycentric blend inside its triangles); LBS of the body's own template with its own weights is the
body's forward pass; a rigid root motion moves a garment rigidly; inverse LBS inverts LBS; diffused
weights (thesis eq. 6.4) are smoother than closest ones and split 50/50 between mirror-symmetric legs.
"""

from __future__ import annotations

import numpy as np
import pytest

from garment_bodies import LEG_R, LEG_X, brute_force_closest, left_right, skirt, two_leg_body
from simgen.body import OPEN_BODY_PATH
from simgen.errors import InputError
from simgen.garment.mesh import unique_edges
from simgen.garment.skinning import (
    closest_body_points,
    compute_skin_weights,
    inverse_lbs,
    laplacian_smooth,
    lbs,
    shape_offsets,
)
from simgen.rotations import axis_angle_to_matrix


@pytest.fixture(scope="module")
def body():
    return two_leg_body()


@pytest.fixture(scope="module")
def skirt_mesh():
    return skirt()


@pytest.fixture(scope="module")
def skirt_weights(body, skirt_mesh):
    v, f = skirt_mesh
    return {
        "closest": compute_skin_weights(v, body, method="closest"),
        "diffused": compute_skin_weights(v, body, method="diffused", faces=f, seed=3),
    }


def _random_pose(rng, n, scale=0.5):
    return rng.uniform(-scale, scale, size=(n, 24, 3))


def _partition_of_unity(w):
    assert w.shape[1] == 24
    assert np.all(w >= 0.0)
    np.testing.assert_allclose(w.sum(axis=1), 1.0, atol=1e-12)


# ----------------------------------------------------------------------------- closest weights
def test_closest_weights_are_the_body_weights_at_body_vertices(body):
    w = compute_skin_weights(body.v_template, body, method="closest")
    np.testing.assert_allclose(w, body.weights, atol=1e-12, rtol=0)


def test_closest_weights_blend_barycentrically_inside_triangles(body):
    rng = np.random.default_rng(1)
    v, f = body.v_template, body.faces
    centroids = v[f].mean(axis=1)
    # Wall triangles of the legs below the torso and of the torso above the legs: nothing else is
    # near them, so a point just outside such a triangle projects into it.
    leg = (np.abs(np.abs(centroids[:, 0]) - LEG_X) < LEG_R + 1e-6) & (centroids[:, 1] < 0.7) & (centroids[:, 1] > 0.05)
    torso = (np.abs(centroids[:, 0]) < 0.05) & (centroids[:, 1] > 1.0) & (centroids[:, 1] < 1.45)
    faces = np.flatnonzero(leg | torso)
    faces = rng.choice(faces, size=60, replace=False)
    bary = rng.dirichlet([2.0, 2.0, 2.0], size=len(faces))
    tri = v[f[faces]]
    normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    points = np.einsum("pc,pcd->pd", bary, tri) + 3e-3 * normal
    expected = np.einsum("pc,pcj->pj", bary, body.weights[f[faces]])
    w = compute_skin_weights(points, body, method="closest")
    np.testing.assert_allclose(w, expected, atol=1e-9, rtol=0)
    near = closest_body_points(points, body)
    np.testing.assert_array_equal(near.face, faces)
    np.testing.assert_allclose(near.distance, 3e-3, atol=1e-5)


def test_closest_weights_agree_with_an_exhaustive_closest_point_search(body):
    rng = np.random.default_rng(11)
    points = rng.uniform([-0.35, -0.05, -0.3], [0.35, 1.6, 0.3], size=(300, 3))
    closest, dist, tri, bary = brute_force_closest(body.v_template, body.faces, points)
    expected = np.einsum("pc,pcj->pj", bary, body.weights[body.faces[tri]])
    near = closest_body_points(points, body)
    np.testing.assert_allclose(np.abs(near.distance), dist, atol=1e-6)
    ours = np.einsum("pc,pcd->pd", near.bary, body.v_template[body.faces[near.face]])
    np.testing.assert_allclose(np.linalg.norm(ours - points, axis=1), dist, atol=1e-9)
    # The same closest point (often on an edge or a vertex, reached from different triangles) must
    # give the same weights; elsewhere the point is on a medial surface, where either answer is right.
    same = np.linalg.norm(ours - closest, axis=1) < 1e-7
    assert same.mean() > 0.95
    w = compute_skin_weights(points, body)
    np.testing.assert_allclose(w[same], expected[same], atol=1e-9)


@pytest.mark.parametrize("method", ["closest", "diffused"])
def test_weights_are_a_partition_of_unity(body, method):
    rng = np.random.default_rng(2)
    points = rng.uniform([-0.4, -0.1, -0.3], [0.4, 1.7, 0.3], size=(300, 3))
    w = compute_skin_weights(points, body, method=method, smoothing_iterations=0, num_samples=16)
    _partition_of_unity(w)


@pytest.mark.skipif(not OPEN_BODY_PATH.is_file(), reason="the open body is not baked")
def test_closest_weights_on_the_open_body():
    from simgen.body import load

    open_body = load("open")
    rng = np.random.default_rng(0)
    idx = rng.choice(open_body.num_vertices, size=500, replace=False)
    w = compute_skin_weights(open_body.v_template[idx], open_body)
    np.testing.assert_allclose(w, open_body.weights[idx] / open_body.weights[idx].sum(axis=1, keepdims=True),
                               atol=1e-9)


# ----------------------------------------------------------------------------- diffused weights
def test_diffused_weights_are_smoother_than_closest(skirt_mesh, skirt_weights):
    _, f = skirt_mesh
    e = unique_edges(f)

    def total_variation(w):
        return float(np.abs(w[e[:, 0]] - w[e[:, 1]]).sum())

    tv_closest = total_variation(skirt_weights["closest"])
    tv_diffused = total_variation(skirt_weights["diffused"])
    assert tv_diffused < 0.8 * tv_closest, (tv_diffused, tv_closest)
    # The worst jump across one edge: closest weights switch legs at the skirt's front and back.
    jump = {k: np.abs(w[e[:, 0]] - w[e[:, 1]]).sum(axis=1).max() for k, w in skirt_weights.items()}
    assert jump["closest"] > 1.0
    assert jump["diffused"] < 0.5 * jump["closest"]
    for w in skirt_weights.values():
        _partition_of_unity(w)


def test_diffused_weights_split_between_the_legs(body, skirt_mesh, skirt_weights):
    # Points midway between the legs: closest follows one leg, diffused draws on both.
    ys = np.linspace(0.2, 0.7, 6)
    mid = np.stack([np.zeros_like(ys), ys, np.zeros_like(ys)], axis=1)
    left, right = left_right(compute_skin_weights(mid, body, method="closest"))
    assert np.all(np.abs(left - right) > 0.99)
    left, right = left_right(compute_skin_weights(mid, body, method="diffused", smoothing_iterations=0))
    np.testing.assert_allclose(left + right, 1.0, atol=1e-12)
    np.testing.assert_allclose(left, 0.5, atol=0.02)
    # On the skirt, the front and back centre lines (x = 0) are shared ~50/50 as well.
    v, _ = skirt_mesh
    centre = np.flatnonzero((np.abs(v[:, 0]) < 1e-9) & (v[:, 1] < 0.62))
    left, right = left_right(skirt_weights["diffused"][centre])
    assert np.all(np.abs(left - right) < 0.1 * (left + right)), np.c_[left, right]
    left, right = left_right(skirt_weights["closest"][centre])
    assert np.all(np.abs(left - right) > 0.9 * (left + right))


def test_diffused_shape_offsets_do_not_tear_at_the_mirror_plane(body):
    # Midway between the legs, thicker legs (beta 1) push a point sideways by the full 1 cm per
    # unit toward whichever leg is "closest"; averaged over both legs (eq. 6.5) it stays put.
    ys = np.linspace(0.2, 0.7, 6)
    mid = np.stack([np.zeros_like(ys), ys, np.zeros_like(ys)], axis=1)
    betas = np.array([0.0, 2.0])
    closest = shape_offsets(mid, body, betas, method="closest")[0]
    diffused = shape_offsets(mid, body, betas)[0]
    np.testing.assert_allclose(np.abs(closest[:, 0]), 0.02, atol=1e-9)
    np.testing.assert_allclose(diffused[:, 0], 0.0, atol=2e-3)
    assert shape_offsets(mid, body, np.zeros(2)).shape == (1, len(mid), 3)


def test_diffused_weights_are_deterministic(body, skirt_mesh, skirt_weights):
    v, f = skirt_mesh
    again = compute_skin_weights(v, body, method="diffused", faces=f, seed=3)
    np.testing.assert_array_equal(again, skirt_weights["diffused"])
    other = compute_skin_weights(v, body, method="diffused", faces=f, seed=4)
    assert not np.array_equal(other, again)
    assert np.abs(other - again).max() < 0.2  # another seed, another estimate of the same average


def test_laplacian_smoothing_keeps_a_partition_of_unity(skirt_mesh):
    v, f = skirt_mesh
    rng = np.random.default_rng(5)
    w = rng.dirichlet(np.full(24, 0.3), size=len(v))
    s = laplacian_smooth(w, f, iterations=7)
    _partition_of_unity(s)
    e = unique_edges(f)
    assert np.abs(s[e[:, 0]] - s[e[:, 1]]).sum() < 0.5 * np.abs(w[e[:, 0]] - w[e[:, 1]]).sum()
    np.testing.assert_array_equal(laplacian_smooth(w, f, iterations=0), w)


def test_bad_arguments_raise_input_error(body, skirt_mesh):
    v, f = skirt_mesh
    with pytest.raises(InputError, match="method"):
        compute_skin_weights(v, body, method="nearest")
    with pytest.raises(InputError, match="faces"):
        compute_skin_weights(v, body, method="diffused")
    with pytest.raises(InputError, match="NaN"):
        compute_skin_weights(np.full((3, 3), np.nan), body)
    with pytest.raises(InputError, match="sigma"):
        compute_skin_weights(v, body, method="diffused", faces=f, sigma=-1.0)
    with pytest.raises(InputError, match="shape"):
        lbs(v, np.ones((len(v), 23)), np.eye(4)[None, None].repeat(24, axis=1))


# ----------------------------------------------------------------------------- LBS
def test_lbs_at_zero_pose_is_the_identity_plus_trans(body, skirt_mesh):
    v, _ = skirt_mesh
    w = compute_skin_weights(v, body)
    trans = np.array([[0.0, 0.0, 0.0], [0.3, -0.2, 1.5]])
    A = body.forward(pose=np.zeros((2, 24, 3)), trans=trans).transforms
    out = lbs(v, w, A)
    assert out.shape == (2, len(v), 3)
    np.testing.assert_allclose(out, v[None] + trans[:, None], atol=1e-12)


def test_lbs_of_the_body_template_is_the_body_forward(body):
    rng = np.random.default_rng(6)
    pose, trans = _random_pose(rng, 3), rng.normal(scale=0.3, size=(3, 3))
    out = body.forward(pose=pose, trans=trans)
    w = compute_skin_weights(body.v_template, body)
    np.testing.assert_allclose(lbs(body.v_template, w, out.transforms), out.vertices, atol=1e-12)


def test_lbs_on_a_shaped_body_uses_the_shape_offsets(body):
    rng = np.random.default_rng(7)
    betas = np.array([[1.5, -2.0], [-1.0, 2.5]])
    pose, trans = _random_pose(rng, 2), rng.normal(scale=0.3, size=(2, 3))
    out = body.forward(betas, pose, trans)
    # On the body surface the closest-point shape offset is the body's own blendshape.
    offsets = shape_offsets(body.v_template, body, betas, method="closest")
    np.testing.assert_allclose(body.v_template[None] + offsets, body.shaped_vertices(betas), atol=1e-12)
    w = compute_skin_weights(body.v_template, body)
    np.testing.assert_allclose(lbs(body.v_template[None] + offsets, w, out.transforms), out.vertices, atol=1e-12)


def test_lbs_moves_a_garment_rigidly_under_a_root_motion(body, skirt_mesh, skirt_weights):
    v, _ = skirt_mesh
    rng = np.random.default_rng(8)
    root = rng.normal(size=(4, 3))
    pose = np.zeros((4, 24, 3))
    pose[:, 0] = root
    trans = rng.normal(size=(4, 3))
    A = body.forward(pose=pose, trans=trans).transforms
    R = axis_angle_to_matrix(root)
    j0 = body.rest_joints()[0, 0]
    expected = np.einsum("nab,vb->nva", R, v - j0) + j0 + trans[:, None]
    for w in skirt_weights.values():
        np.testing.assert_allclose(lbs(v, w, A), expected, atol=1e-12)


def test_inverse_lbs_inverts_lbs(body, skirt_mesh, skirt_weights):
    v, _ = skirt_mesh
    rng = np.random.default_rng(9)
    A = body.forward(pose=_random_pose(rng, 5, scale=1.0), trans=rng.normal(size=(5, 3))).transforms
    # Per-frame rest shapes (a garment with wrinkles, as thesis eq. 4.5 unposes them).
    rest = v[None] + rng.normal(scale=0.01, size=(5, len(v), 3))
    for w in skirt_weights.values():
        posed = lbs(rest, w, A)
        np.testing.assert_allclose(inverse_lbs(posed, w, A), rest, atol=1e-10, rtol=0)
    # One frame without a batch axis.
    w = skirt_weights["diffused"]
    np.testing.assert_allclose(inverse_lbs(lbs(v, w, A[0])[0], w, A[0])[0], v, atol=1e-10)
