"""Operations on motion clips: interpolation at any time, resampling, mirroring, blending, placement.

All functions are pure: they return new :class:`MotionClip` objects and never modify their input.
Rotations are interpolated by quaternion slerp along the shorter arc, translations linearly. Clips
returned by :func:`resample`, :func:`mirror`, :func:`blend_from_rest`, :func:`trim`,
:func:`apply_world_rotation`, :func:`put_on_floor` and :func:`concatenate` keep the input's meta
and append a record of the operation to ``meta["history"]``.
"""

from __future__ import annotations

import copy

import numpy as np

from simgen.body.model import NUM_JOINTS, SMPL_JOINT_NAMES, BodyModel
from simgen.errors import InputError
from simgen.motion.clip import MotionClip
from simgen.rotations import (
    axis_angle_to_matrix,
    axis_angle_to_quat,
    matrix_to_axis_angle,
    quat_slerp,
    quat_to_axis_angle,
)

__all__ = [
    "poses_at",
    "pose_at",
    "quats_at",
    "resample",
    "mirror",
    "blend_from_rest",
    "apply_world_rotation",
    "put_on_floor",
    "foot_vertex_indices",
    "lowest_foot_heights",
    "posed_joints",
    "trim",
    "concatenate",
    "MIRROR_JOINTS",
    "LOADER_MAX_SINK",
]

# SMPL joint index of each joint's left/right twin (itself for joints on the midline).
MIRROR_JOINTS = np.array(
    [SMPL_JOINT_NAMES.index(n.replace("left_", "@").replace("right_", "left_").replace("@", "right_"))
     for n in SMPL_JOINT_NAMES],
    dtype=np.int64,
)

# How far below the floor [m] a loader lets a foot sink before it lifts the body in those frames
# (put_on_floor's max_sink): ordinary capture noise stays untouched, toes pointed into the ground do not.
LOADER_MAX_SINK = 0.02

# Joints whose skinned vertices form the feet (used to find the lowest foot point quickly).
_FOOT_JOINTS = [SMPL_JOINT_NAMES.index(n) for n in ("left_ankle", "right_ankle", "left_foot", "right_foot")]


def _with_history(meta: dict, entry: dict) -> dict:
    """A deep copy of meta with one more entry in meta['history'] (the input clip is left untouched)."""
    out = copy.deepcopy(meta)
    out["history"] = list(out.get("history", [])) + [entry]
    return out


# ---------------------------------------------------------------------------------------- sampling
def _frame_coordinates(clip: MotionClip, times) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Neighbouring frame indices i0, i1 (K,) and blend weights alpha (K,) in [0, 1] for times [s]."""
    t = np.asarray(times, dtype=np.float64).reshape(-1)
    if not np.all(np.isfinite(t)):
        raise InputError(f"motion {clip.name!r}: sample times must be finite, got {t[~np.isfinite(t)][:3]}")
    f = np.clip(t * clip.fps, 0.0, clip.num_frames - 1)
    # Times that are frame times up to rounding (e.g. 0.1 * 30) must return the frame itself exactly.
    nearest = np.rint(f)
    f = np.where(np.abs(f - nearest) < 1e-9, nearest, f)
    i0 = np.floor(f).astype(np.int64)
    i1 = np.minimum(i0 + 1, clip.num_frames - 1)
    return i0, i1, f - i0


def quats_at(clip: MotionClip, times) -> np.ndarray:
    """Joint rotations as unit quaternions (w, x, y, z) at arbitrary times, shape (K, 24, 4).

    times [s], shape (K,) (a scalar gives K = 1); times outside [0, duration] are clamped to the
    first/last frame. Between frames the rotation is the slerp of the two neighbouring frames.
    Consecutive quaternions along K lie in the same hemisphere (q[k] . q[k-1] >= 0, q[0] has w >= 0),
    so a consumer that interpolates them linearly (the Warp body) never takes the long way round.
    """
    i0, i1, alpha = _frame_coordinates(clip, times)
    q0 = axis_angle_to_quat(clip.poses[i0])  # (K, 24, 4)
    q1 = axis_angle_to_quat(clip.poses[i1])
    q = quat_slerp(q0, q1, alpha[:, None])
    q = np.where(q[:1, :, :1] < 0.0, -q, q) if q.shape[0] else q
    if q.shape[0] > 1:
        dots = np.sum(q[1:] * q[:-1], axis=-1)  # (K-1, 24), signs relative to the unflipped predecessor
        sign = np.cumprod(np.where(dots < 0.0, -1.0, 1.0), axis=0)
        q[1:] *= sign[..., None]
    return q


def poses_at(clip: MotionClip, times) -> tuple[np.ndarray, np.ndarray]:
    """Poses and root translations at arbitrary times (slerp / linear between neighbouring frames).

    times [s], shape (K,) or scalar; clamped to [0, duration].
    Returns (poses axis-angle [rad], shape (K, 24, 3); trans [m], shape (K, 3)). At frame times the
    frames themselves are returned.
    """
    i0, i1, alpha = _frame_coordinates(clip, times)
    q = quat_slerp(axis_angle_to_quat(clip.poses[i0]), axis_angle_to_quat(clip.poses[i1]), alpha[:, None])
    poses = quat_to_axis_angle(q)
    exact = alpha == 0.0
    poses[exact] = clip.poses[i0[exact]]  # keep the stored axis-angle (angles > pi stay as they were)
    trans = (1.0 - alpha)[:, None] * clip.trans[i0] + alpha[:, None] * clip.trans[i1]
    return poses, trans


def pose_at(clip: MotionClip, t: float) -> tuple[np.ndarray, np.ndarray]:
    """Pose axis-angle [rad], shape (24, 3), and trans [m], shape (3,), at time t [s] (see poses_at)."""
    poses, trans = poses_at(clip, np.array([float(t)]))
    return poses[0], trans[0]


def resample(clip: MotionClip, fps: float) -> MotionClip:
    """The clip sampled at a new frame rate fps [1/s] over the same duration.

    The new clip has round(duration * fps) + 1 frames at times k / fps (the last one clamped to the
    clip's end), so its duration matches the original to within half a new frame.
    """
    try:
        fps = float(fps)
    except (TypeError, ValueError):
        raise InputError(f"motion {clip.name!r}: resample fps must be a number, got {fps!r}") from None
    if not np.isfinite(fps) or fps <= 0.0:
        raise InputError(f"motion {clip.name!r}: resample fps must be positive, got {fps}")
    n = int(round(clip.duration * fps)) + 1
    times = np.minimum(np.arange(n) / fps, clip.duration)
    poses, trans = poses_at(clip, times)
    meta = _with_history(clip.meta, {"op": "resample", "from_fps": clip.fps, "to_fps": fps})
    return MotionClip(clip.name, fps, poses, trans, meta)


# ---------------------------------------------------------------------------------------- mirroring
def mirror(clip: MotionClip) -> MotionClip:
    """Left-right mirror image across the body's sagittal plane (x -> -x in SMPL's frame).

    Left and right joints swap; each rotation R becomes M R M with M = diag(-1, 1, 1), i.e. axis-angle
    (x, y, z) -> (x, -y, -z); trans x -> -x. For a left-right symmetric body (rest pelvis at x = 0)
    the posed mirrored body is exactly the x-reflection of the posed original.
    """
    poses = clip.poses[:, MIRROR_JOINTS] * np.array([1.0, -1.0, -1.0])
    trans = clip.trans * np.array([-1.0, 1.0, 1.0])
    return MotionClip(clip.name, clip.fps, poses, trans, _with_history(clip.meta, {"op": "mirror"}))


# ---------------------------------------------------------------------------------------- blending
def blend_from_rest(clip: MotionClip, num_frames: int, *, rest_pose=None) -> MotionClip:
    """Prepend num_frames frames that move smoothly from a rest pose to the clip's first frame.

    Prepended frame k (k = 0 .. num_frames-1) is slerp(rest, first, s(k / num_frames)) per joint with
    the ease-in-out s(u) = (1 - cos(pi u)) / 2, so frame 0 is the rest pose itself and the motion
    starts and arrives without a jump; trans stays at the first frame's trans. rest_pose: axis-angle
    [rad], shape (24, 3) (default zeros: SMPL's rest pose, global orientation included).
    """
    if isinstance(num_frames, bool) or int(num_frames) != num_frames or num_frames < 0:
        raise InputError(f"motion {clip.name!r}: blend num_frames must be a non-negative integer, got {num_frames!r}")
    num_frames = int(num_frames)
    rest = np.zeros((NUM_JOINTS, 3)) if rest_pose is None else np.asarray(rest_pose, dtype=np.float64)
    if rest.shape != (NUM_JOINTS, 3) or not np.all(np.isfinite(rest)):
        raise InputError(f"motion {clip.name!r}: rest_pose must be finite with shape (24, 3), got {rest.shape}")
    u = np.arange(num_frames) / max(num_frames, 1)
    s = 0.5 * (1.0 - np.cos(np.pi * u))
    q = quat_slerp(axis_angle_to_quat(rest)[None], axis_angle_to_quat(clip.poses[0])[None], s[:, None])
    lead = quat_to_axis_angle(q).reshape(num_frames, NUM_JOINTS, 3)
    if num_frames:
        lead[0] = rest
    poses = np.concatenate([lead, clip.poses])
    trans = np.concatenate([np.repeat(clip.trans[:1], num_frames, axis=0), clip.trans])
    meta = _with_history(clip.meta, {"op": "blend_from_rest", "num_frames": num_frames})
    return MotionClip(clip.name, clip.fps, poses, trans, meta)


# ---------------------------------------------------------------------------------------- placement
def apply_world_rotation(clip: MotionClip, R, rest_pelvis) -> MotionClip:
    """Rotate the whole motion by the world rotation R (the root-translation rule, docs/architecture.md, "Motions").

    R: rotation matrix, shape (3, 3); rest_pelvis: the body's rest pelvis joint J0 [m], shape (3,).
    global_orient -> R * global_orient, trans -> R (trans + J0) - J0, so every posed vertex v becomes
    R v exactly (posed vertex = R_0 (v - J0) + J0 + trans).
    """
    R = np.asarray(R, dtype=np.float64)
    J0 = np.asarray(rest_pelvis, dtype=np.float64).reshape(-1)
    if R.shape != (3, 3) or not np.allclose(R @ R.T, np.eye(3), atol=1e-6) or np.linalg.det(R) < 0.0:
        raise InputError(f"motion {clip.name!r}: world rotation must be a proper 3x3 rotation matrix")
    if J0.shape != (3,) or not np.all(np.isfinite(J0)):
        raise InputError(f"motion {clip.name!r}: rest_pelvis must be a finite 3-vector, got shape {J0.shape}")
    poses = clip.poses.copy()
    poses[:, 0] = matrix_to_axis_angle(R @ axis_angle_to_matrix(clip.poses[:, 0]))
    trans = (clip.trans + J0) @ R.T - J0
    meta = _with_history(clip.meta, {"op": "world_rotation", "R": R.round(12).tolist()})
    return MotionClip(clip.name, clip.fps, poses, trans, meta)


def foot_vertex_indices(body: BodyModel) -> np.ndarray:
    """Indices of the vertices skinned mainly (weight > 0.5) to the ankles and feet, shape (K,).

    Falls back to all vertices for a body whose feet carry no such weights.
    """
    idx = np.flatnonzero(body.weights[:, _FOOT_JOINTS].sum(axis=1) > 0.5)
    return idx if idx.size else np.arange(body.num_vertices)


def _subset_body(body: BodyModel, betas, vertex_ids: np.ndarray) -> BodyModel:
    """A body with only some vertices of `body` (already shaped by betas) but the same joints.

    The 24 rest joints of the full shaped body are appended as extra vertices that the joint regressor
    picks out one to one, so forward() on the subset poses those vertices exactly as on the full body
    at a fraction of the cost.
    """
    v_shaped = body.shaped_vertices(np.zeros(body.num_betas) if betas is None else betas)[0]
    joints = body.J_regressor @ v_shaped
    n = vertex_ids.size
    posedirs = body.posedirs[vertex_ids]
    posedirs = np.concatenate([posedirs, np.zeros((NUM_JOINTS, 3, posedirs.shape[2]))])
    J_reg = np.zeros((NUM_JOINTS, n + NUM_JOINTS))
    J_reg[:, n:] = np.eye(NUM_JOINTS)
    return BodyModel(
        v_template=np.concatenate([v_shaped[vertex_ids], joints]),
        shapedirs=np.zeros((n + NUM_JOINTS, 3, 0)),
        posedirs=posedirs,
        J_regressor=J_reg,
        weights=np.concatenate([body.weights[vertex_ids], np.eye(NUM_JOINTS)]),
        parents=body.parents,
        faces=np.array([[n, n + 1, n + 2]]),
        name=f"{body.name}-subset",
    )


def lowest_foot_heights(clip: MotionClip, body: BodyModel, *, betas=None, frames=None) -> np.ndarray:
    """Height [m] of the lowest foot vertex of the posed body in each of the given frames, shape (K,).

    frames: frame indices (default: all frames).
    """
    frames = np.arange(clip.num_frames) if frames is None else np.asarray(frames, dtype=np.int64).reshape(-1)
    ids = foot_vertex_indices(body)
    sub = _subset_body(body, betas, ids)
    out = np.empty(frames.size)
    for start in range(0, frames.size, 256):  # bounded memory for long clips
        f = frames[start : start + 256]
        verts = sub.forward(pose=clip.poses[f], trans=clip.trans[f]).vertices[:, : ids.size]
        out[start : start + 256] = verts[..., 1].min(axis=1)
    return out


def posed_joints(clip: MotionClip, body: BodyModel, *, betas=None) -> np.ndarray:
    """World positions [m] of the 24 posed joints in every frame, shape (T, 24, 3), without posing
    the mesh (cheap for long clips)."""
    sub = _subset_body(body, betas, np.zeros(0, dtype=np.int64))
    return np.concatenate([sub.forward(pose=clip.poses[s : s + 1024], trans=clip.trans[s : s + 1024]).joints
                           for s in range(0, clip.num_frames, 1024)])


def put_on_floor(
    clip: MotionClip,
    body: BodyModel,
    *,
    betas=None,
    num_frames: int | None = None,
    max_sink: float | None = None,
    lift_ramp_s: float = 0.25,
) -> MotionClip:
    """Shift trans along y so that the lowest foot point over the first frames is at y = 0.

    body: the body the clip will animate; betas: its shape, shape (B',) (default zeros).
    num_frames: how many leading frames to consider (default: the first 0.5 s, at least one frame).
    max_sink [m]: when given, frames in which a foot would still sink more than max_sink below the
      floor (motion capture often has such dips: a toe pointed into the ground) are lifted just enough,
      with the lift faded in and out over lift_ramp_s [s] on each side (raised-cosine ramps) so that
      the root does not jump. None leaves every frame at the constant shift.
    Only the vertices skinned mainly to the ankles and feet are posed (see foot_vertex_indices).
    """
    if num_frames is None:
        num_frames = max(1, int(round(0.5 * clip.fps)))
    if isinstance(num_frames, bool) or int(num_frames) != num_frames or num_frames < 1:
        raise InputError(f"motion {clip.name!r}: put_on_floor num_frames must be a positive integer, "
                         f"got {num_frames!r}")
    frames = None if max_sink is not None else np.arange(min(int(num_frames), clip.num_frames))
    lows = lowest_foot_heights(clip, body, betas=betas, frames=frames)
    shift = -float(lows[: int(num_frames)].min())
    trans = clip.trans.copy()
    trans[:, 1] += shift
    entry = {"op": "put_on_floor", "shift_y": shift, "frames": int(min(num_frames, clip.num_frames))}
    if max_sink is not None:
        if not np.isfinite(max_sink) or max_sink < 0.0:
            raise InputError(f"motion {clip.name!r}: put_on_floor max_sink must be >= 0, got {max_sink}")
        lift = _lift_profile(np.maximum(0.0, -(lows + shift) - max_sink), lift_ramp_s * clip.fps)
        trans[:, 1] += lift
        entry.update(max_sink=float(max_sink), max_lift=float(lift.max()), lifted_frames=int(np.sum(lift > 0.0)))
    meta = _with_history(clip.meta, entry)
    return MotionClip(clip.name, clip.fps, clip.poses.copy(), trans, meta)


def _lift_profile(depth: np.ndarray, ramp_frames: float) -> np.ndarray:
    """Smallest upper envelope of raised-cosine bumps that covers depth, shape (T,) -> (T,).

    Each frame k with depth d_k > 0 contributes d_k * w(t - k), w(0) = 1 falling to 0 at |t - k| =
    ramp_frames; the profile is the maximum over k, hence >= depth everywhere and continuous.
    """
    lift = np.zeros_like(depth)
    hot = np.flatnonzero(depth > 0.0)
    if hot.size == 0:
        return lift
    t = np.arange(depth.size)
    r = max(float(ramp_frames), 1.0)
    for k in hot:  # few frames dip in practice; each bump touches at most 2 r + 1 frames
        lo, hi = max(0, int(k - r)), min(depth.size, int(k + r) + 1)
        u = np.abs(t[lo:hi] - k) / r
        lift[lo:hi] = np.maximum(lift[lo:hi], depth[k] * 0.5 * (1.0 + np.cos(np.pi * np.minimum(u, 1.0))))
    return lift


# ---------------------------------------------------------------------------------------- editing
def trim(clip: MotionClip, start_s: float, end_s: float) -> MotionClip:
    """The frames with times in [start_s, end_s] [s] (frame times within 1e-9 s of a bound count).

    Raises InputError when the interval holds no frame or start_s > end_s.
    """
    start_s, end_s = float(start_s), float(end_s)
    if not (np.isfinite(start_s) and np.isfinite(end_s)) or start_s > end_s:
        raise InputError(f"motion {clip.name!r}: trim interval [{start_s}, {end_s}] s is not a valid interval")
    t = clip.times
    keep = np.flatnonzero((t >= start_s - 1e-9) & (t <= end_s + 1e-9))
    if keep.size == 0:
        raise InputError(f"motion {clip.name!r}: trim interval [{start_s}, {end_s}] s holds no frame "
                         f"(clip spans 0 to {clip.duration:.3f} s)")
    meta = _with_history(clip.meta, {"op": "trim", "start_s": start_s, "end_s": end_s})
    return MotionClip(clip.name, clip.fps, clip.poses[keep], clip.trans[keep], meta)


def concatenate(clips, *, name: str | None = None) -> MotionClip:
    """Clips played one after the other at the first clip's frame rate (others are resampled).

    Poses and translations are joined as they are (no blending or re-alignment at the seams).
    """
    clips = list(clips)
    if not clips:
        raise InputError("concatenate needs at least one motion clip")
    fps = clips[0].fps
    parts = [c if c.fps == fps else resample(c, fps) for c in clips]
    meta = _with_history(clips[0].meta, {"op": "concatenate", "clips": [c.name for c in clips]})
    return MotionClip(name or clips[0].name, fps, np.concatenate([c.poses for c in parts]),
                      np.concatenate([c.trans for c in parts]), meta)
