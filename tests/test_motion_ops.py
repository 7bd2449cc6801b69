"""Tests of simgen.motion.ops: interpolation, resampling, mirroring, blending, world rotation, floor.

References are independent of the code under test: scipy's Rotation for slerp midpoints, analytic
uniform rotations, exact reflections of a left-right symmetric body, and the full body forward pass.
Also defines ``stick_body()``, a small synthetic SMPL-format body used by test_motion_loaders.py.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from simgen.body.model import SMPL_JOINT_NAMES, SMPL_PARENTS, BodyModel
from simgen.errors import InputError
from simgen.motion import (
    MotionClip,
    apply_world_rotation,
    blend_from_rest,
    concatenate,
    mirror,
    pose_at,
    poses_at,
    put_on_floor,
    quats_at,
    resample,
    trim,
)
from simgen.motion.ops import MIRROR_JOINTS, foot_vertex_indices, lowest_foot_heights
from simgen.rotations import axis_angle_to_matrix, axis_angle_to_quat

# ---------------------------------------------------------------------------------------- test body
# Rest joints of a T-posed adult [m] (Y-up, front +Z, left +X), left side and midline; the right
# side is the mirror image. Leaves get an end point so that their segment has a direction.
_LEFT_JOINTS = {
    "pelvis": (0.0, 0.95, 0.0), "left_hip": (0.09, 0.86, 0.0), "spine1": (0.0, 1.06, -0.02),
    "left_knee": (0.10, 0.50, 0.01), "spine2": (0.0, 1.19, -0.01), "left_ankle": (0.10, 0.09, -0.03),
    "spine3": (0.0, 1.25, 0.0), "left_foot": (0.11, 0.03, 0.10), "neck": (0.0, 1.47, -0.03),
    "left_collar": (0.08, 1.39, -0.01), "head": (0.0, 1.58, 0.02), "left_shoulder": (0.18, 1.42, -0.02),
    "left_elbow": (0.44, 1.42, -0.03), "left_wrist": (0.70, 1.42, -0.03), "left_hand": (0.79, 1.42, -0.03),
}
_LEAF_ENDS = {"left_foot": (0.11, 0.03, 0.17), "head": (0.0, 1.75, 0.02), "left_hand": (0.88, 1.42, -0.03)}
_RADII = {"pelvis": 0.12, "spine1": 0.12, "spine2": 0.12, "spine3": 0.12, "neck": 0.05, "head": 0.08, "hip": 0.07,
          "knee": 0.05, "ankle": 0.035, "foot": 0.025, "collar": 0.05, "shoulder": 0.045, "elbow": 0.035,
          "wrist": 0.03, "hand": 0.02}
_REFLECT = np.array([-1.0, 1.0, 1.0])


def stick_body() -> BodyModel:
    """A left-right symmetric SMPL-format body: a tube of 3 rings x 8 vertices along each joint's
    segment (rigidly skinned, the last ring blended 70/30 with the child) plus one vertex at each
    joint, which the joint regressor picks out. Two shape components (overall scale, width)."""
    joints = np.array([_LEFT_JOINTS[n] if n in _LEFT_JOINTS else
                       np.array(_LEFT_JOINTS[n.replace("right_", "left_")]) * _REFLECT for n in SMPL_JOINT_NAMES])
    child = {0: 3, 9: 12}
    for c in range(1, 24):
        child.setdefault(int(SMPL_PARENTS[c]), c)
    angles = 2.0 * np.pi * np.arange(8) / 8
    left_tubes: dict[int, tuple[np.ndarray, np.ndarray]] = {}
    verts, weights, faces = [], [], []
    for i, name in enumerate(SMPL_JOINT_NAMES):
        if name.startswith("right_"):
            twin = SMPL_JOINT_NAMES.index(name.replace("right_", "left_"))
            pts, w = left_tubes[twin]
            pts, w = pts * _REFLECT, w[:, MIRROR_JOINTS]
        else:
            a = joints[i]
            b = joints[child[i]] if i in child else np.array(_LEAF_ENDS[name])
            d = b - a
            u = np.array([1.0, 0.0, 0.0]) if a[0] == 0.0 else np.cross(d, [0.0, 1.0, 0.3])
            u = u - d * (u @ d) / (d @ d)
            u /= np.linalg.norm(u)
            v = np.cross(d, u) / np.linalg.norm(d)
            radius = _RADII[name.split("_")[-1]]
            pts, w = [], []
            for frac, own in ((0.15, 1.0), (0.5, 1.0), (0.85, 0.7)):
                for t in angles:
                    pts.append(a + frac * d + radius * (np.cos(t) * u + np.sin(t) * v))
                    row = np.zeros(24)
                    row[i] += own
                    row[child.get(i, i)] += 1.0 - own
                    w.append(row)
            pts, w = np.array(pts), np.array(w)
            left_tubes[i] = (pts, w)
        base = sum(len(p) for p in verts)
        verts.append(pts)
        weights.append(w)
        for ring in range(2):
            for k in range(8):
                a0, a1 = base + ring * 8 + k, base + ring * 8 + (k + 1) % 8
                faces += [(a0, a1, a1 + 8), (a0, a1 + 8, a0 + 8)]
    V = np.concatenate(verts + [joints])
    W = np.concatenate(weights + [np.eye(24)])
    V[:, 1] -= V[:, 1].min()
    n_tube = V.shape[0] - 24
    J_reg = np.zeros((24, V.shape[0]))
    J_reg[:, n_tube:] = np.eye(24)
    shapedirs = np.zeros((V.shape[0], 3, 2))
    shapedirs[:, :, 0] = 0.05 * V
    shapedirs[:, 0, 1] = 0.05 * V[:, 0]
    return BodyModel(V, shapedirs, np.zeros((V.shape[0], 3, 0)), J_reg, W, SMPL_PARENTS, np.array(faces),
                     name="stick")


def random_clip(seed: int = 0, frames: int = 12, fps: float = 30.0, scale: float = 0.6) -> MotionClip:
    """A clip of random rotations (angles up to ~scale * sqrt(3) rad) and translations."""
    rng = np.random.default_rng(seed)
    poses = rng.normal(scale=scale, size=(frames, 24, 3))
    trans = rng.normal(scale=0.3, size=(frames, 3))
    return MotionClip("random", fps, poses, trans, {"source": "test"})


@pytest.fixture(scope="module")
def body() -> BodyModel:
    return stick_body()


def _rotations_close(a, b, atol=1e-9) -> bool:
    """Axis-angle arrays a, b describe the same rotations (compared as matrices)."""
    return np.allclose(axis_angle_to_matrix(a), axis_angle_to_matrix(b), atol=atol)


# ---------------------------------------------------------------------------------------- sampling
def test_poses_at_frame_times_returns_the_frames():
    clip = random_clip()
    poses, trans = poses_at(clip, clip.times)
    np.testing.assert_array_equal(poses, clip.poses)
    np.testing.assert_allclose(trans, clip.trans, atol=1e-15)


def test_slerp_midpoint_is_the_half_rotation():
    clip = random_clip(seed=1, frames=5, fps=24.0)
    times = (np.arange(4) + 0.5) / clip.fps
    poses, trans = poses_at(clip, times)
    for k in range(4):
        r0 = Rotation.from_rotvec(clip.poses[k])
        r1 = Rotation.from_rotvec(clip.poses[k + 1])
        half = r0 * Rotation.from_rotvec(0.5 * (r0.inv() * r1).as_rotvec())  # scipy: shortest arc
        assert _rotations_close(poses[k], half.as_rotvec())
        np.testing.assert_allclose(trans[k], 0.5 * (clip.trans[k] + clip.trans[k + 1]), atol=1e-12)


def test_uniform_rotation_is_interpolated_exactly_and_clamped():
    # A joint turning at a constant rate about a fixed axis: slerp reproduces the angle at any time.
    fps, omega = 10.0, 2.0  # [1/s], [rad/s]
    axis = np.array([1.0, 2.0, -2.0]) / 3.0
    t = np.arange(11) / fps
    poses = np.zeros((11, 24, 3))
    poses[:, 18] = (omega * t)[:, None] * axis
    clip = MotionClip("spin", fps, poses, np.zeros((11, 3)))
    q = np.linspace(0.0, clip.duration, 37)
    got, _ = poses_at(clip, q)
    np.testing.assert_allclose(got[:, 18], (omega * q)[:, None] * axis, atol=1e-12)
    first, _ = pose_at(clip, -1.0)
    last, _ = pose_at(clip, clip.duration + 5.0)
    np.testing.assert_array_equal(first, poses[0])
    np.testing.assert_array_equal(last, poses[-1])


def test_quats_at_matches_poses_and_keeps_one_hemisphere():
    rng = np.random.default_rng(3)
    poses = np.cumsum(rng.normal(scale=0.9, size=(20, 24, 3)), axis=0)  # large turns, angles > pi
    clip = MotionClip("turns", 30.0, poses, np.zeros((20, 3)))
    times = np.linspace(-0.1, clip.duration + 0.1, 97)
    q = quats_at(clip, times)
    assert q.shape == (97, 24, 4)
    np.testing.assert_allclose(np.linalg.norm(q, axis=-1), 1.0, atol=1e-12)
    assert np.all(np.sum(q[1:] * q[:-1], axis=-1) >= 0.0)
    assert np.all(q[0, :, 0] >= 0.0)
    ref = axis_angle_to_quat(poses_at(clip, times)[0])
    np.testing.assert_allclose(np.abs(np.sum(q * ref, axis=-1)), 1.0, atol=1e-9)


def test_nonfinite_times_are_rejected():
    with pytest.raises(InputError):
        poses_at(random_clip(), [0.0, np.nan])


# ---------------------------------------------------------------------------------------- resampling
def test_resample_round_trip_30_120_30():
    clip = random_clip(seed=4, frames=31)
    up = resample(clip, 120.0)
    assert up.num_frames == 121 and up.duration == pytest.approx(clip.duration)
    down = resample(up, 30.0)
    assert down.num_frames == clip.num_frames
    assert _rotations_close(down.poses, clip.poses, atol=1e-9)
    np.testing.assert_allclose(down.trans, clip.trans, atol=1e-12)
    # the 120 fps clip passes through every original frame
    assert _rotations_close(up.poses[::4], clip.poses, atol=1e-9)
    assert [h["op"] for h in down.meta["history"]] == ["resample", "resample"]
    assert down.meta["source"] == "test" and "history" not in clip.meta


def test_resample_keeps_duration_for_non_integer_ratios():
    clip = random_clip(seed=5, frames=100, fps=120.0)  # 0.825 s
    out = resample(clip, 30.0)
    assert abs(out.duration - clip.duration) <= 0.5 / 30.0
    np.testing.assert_allclose(out.trans[-1], clip.trans[-1])


@pytest.mark.parametrize("fps", [0.0, -30.0, np.inf, "fast"])
def test_resample_rejects_bad_fps(fps):
    with pytest.raises(InputError):
        resample(random_clip(), fps)


# ---------------------------------------------------------------------------------------- mirroring
def test_mirror_twice_is_identity():
    clip = random_clip(seed=6)
    back = mirror(mirror(clip))
    np.testing.assert_array_equal(back.poses, clip.poses)
    np.testing.assert_array_equal(back.trans, clip.trans)


def test_mirrored_body_is_the_reflection_of_the_original(body):
    V = body.v_template
    # vertex i of the mirrored body corresponds to vertex perm[i] of the original
    d = np.linalg.norm((V * _REFLECT)[:, None] - V[None], axis=-1)
    perm = np.argmin(d, axis=1)
    assert np.all(d[np.arange(len(V)), perm] < 1e-12) and len(set(perm.tolist())) == len(V)
    clip = random_clip(seed=7, frames=6)
    a = body.forward(pose=clip.poses, trans=clip.trans).vertices
    m = mirror(clip)
    b = body.forward(pose=m.poses, trans=m.trans).vertices
    np.testing.assert_allclose(b, (a * _REFLECT)[:, perm], atol=1e-12)


# ---------------------------------------------------------------------------------------- blending
def test_blend_from_rest_starts_at_rest_and_eases_into_the_clip():
    clip = random_clip(seed=8, frames=5)
    n = 10
    out = blend_from_rest(clip, n)
    assert out.num_frames == n + clip.num_frames
    np.testing.assert_array_equal(out.poses[0], 0.0)
    np.testing.assert_array_equal(out.poses[n:], clip.poses)
    np.testing.assert_array_equal(out.trans[: n + 1], np.repeat(clip.trans[:1], n + 1, axis=0))
    # per joint, the angle from rest grows as (1 - cos(pi u)) / 2 of the final angle (slerp on one arc)
    target = np.linalg.norm(Rotation.from_rotvec(clip.poses[0]).as_rotvec(), axis=-1)
    u = np.arange(n + 1) / n
    angles = np.linalg.norm(Rotation.from_rotvec(out.poses[: n + 1].reshape(-1, 3)).as_rotvec(), axis=-1)
    np.testing.assert_allclose(angles.reshape(n + 1, 24), np.outer(0.5 * (1 - np.cos(np.pi * u)), target),
                               atol=1e-9)
    assert blend_from_rest(clip, 0).num_frames == clip.num_frames
    with pytest.raises(InputError):
        blend_from_rest(clip, -1)


def test_blend_from_a_given_rest_pose():
    clip = random_clip(seed=9, frames=3)
    rest = random_clip(seed=10, frames=1).poses[0]
    out = blend_from_rest(clip, 4, rest_pose=rest)
    np.testing.assert_array_equal(out.poses[0], rest)
    with pytest.raises(InputError):
        blend_from_rest(clip, 4, rest_pose=np.zeros((23, 3)))


# ---------------------------------------------------------------------------------------- placement
def test_world_rotation_rotates_every_posed_vertex(body):
    clip = random_clip(seed=11, frames=4)
    R = Rotation.from_rotvec([0.3, -1.2, 0.8]).as_matrix()
    J0 = body.rest_joints()[0, 0]
    a = body.forward(pose=clip.poses, trans=clip.trans).vertices
    out = apply_world_rotation(clip, R, J0)
    b = body.forward(pose=out.poses, trans=out.trans).vertices
    np.testing.assert_allclose(b, a @ R.T, atol=1e-12)
    with pytest.raises(InputError):
        apply_world_rotation(clip, np.diag([1.0, 1.0, -1.0]), J0)  # a reflection


def test_put_on_floor_puts_the_lowest_foot_point_of_the_first_frames_at_zero(body):
    clip = random_clip(seed=12, frames=30, scale=0.2)
    out = put_on_floor(clip, body, num_frames=10)
    verts = body.forward(pose=out.poses, trans=out.trans).vertices
    feet = foot_vertex_indices(body)
    assert len(feet) < body.num_vertices
    assert verts[:10, feet, 1].min() == pytest.approx(0.0, abs=1e-12)
    # the fast foot-only posing equals the full forward pass
    np.testing.assert_allclose(lowest_foot_heights(out, body), verts[:, feet, 1].min(axis=1), atol=1e-12)
    np.testing.assert_allclose(out.trans[:, [0, 2]], clip.trans[:, [0, 2]])
    assert np.ptp(out.trans[:, 1] - clip.trans[:, 1]) < 1e-12  # one constant shift


def test_put_on_floor_with_shape(body):
    clip = random_clip(seed=13, frames=8, scale=0.2)
    betas = np.array([1.5, -1.0])
    out = put_on_floor(clip, body, betas=betas, num_frames=3)
    verts = body.forward(betas, out.poses, out.trans).vertices
    assert verts[:3, foot_vertex_indices(body), 1].min() == pytest.approx(0.0, abs=1e-12)


def test_put_on_floor_lifts_frames_that_sink_too_deep(body):
    clip = random_clip(seed=14, frames=60, scale=0.05)
    trans = clip.trans.copy()
    trans[:, 1] = 0.0
    trans[30:34, 1] -= 0.08  # a dip in the middle of the clip
    clip = MotionClip("dip", 30.0, clip.poses, trans)
    plain = put_on_floor(clip, body)
    lifted = put_on_floor(clip, body, max_sink=0.02, lift_ramp_s=0.2)
    low_plain = lowest_foot_heights(plain, body)
    low = lowest_foot_heights(lifted, body)
    assert low_plain.min() < -0.05
    assert low.min() >= -0.02 - 1e-12
    np.testing.assert_array_equal(lifted.trans[:15], plain.trans[:15])  # far from the dip: untouched
    lift = lifted.trans[:, 1] - plain.trans[:, 1]
    assert np.all(lift >= 0.0) and np.max(np.abs(np.diff(lift))) < 0.05  # ramps, no jumps
    assert lifted.meta["history"][-1]["lifted_frames"] > 4


# ---------------------------------------------------------------------------------------- editing
def test_trim_and_concatenate():
    clip = random_clip(seed=15, frames=31)
    part = trim(clip, 0.2, 0.5)
    np.testing.assert_array_equal(part.poses, clip.poses[6:16])
    with pytest.raises(InputError):
        trim(clip, 0.5, 0.2)
    with pytest.raises(InputError):
        trim(clip, 2.0, 3.0)
    both = concatenate([part, resample(part, 60.0)])
    assert both.fps == 30.0 and both.num_frames == 2 * part.num_frames
    np.testing.assert_allclose(both.trans[part.num_frames:], part.trans, atol=1e-12)
