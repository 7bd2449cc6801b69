"""Keep a clip's arms out of the torso: turn each upper arm away from the body where the skinned arm sinks in.

A clip made for one skeleton (motion capture, retargeted) and played on another body's proportions
often lets the arms hang a few centimetres inside the torso and the hands inside the hips: the
actor's arms touched their sides, this body's sides are wider. A skinned body without pose
correctives has no contact, so nothing stops it. For a cloth simulation that is a real problem: cloth
between arm and torso cannot be outside both (the solver's body-part rule keeps it on its own part,
which then lies inside the other), sleeves and torso are pulled into each other and stretch.

:func:`separate_arms` fixes the motion, not the cloth. In every frame where points of an arm lie
inside the torso or a leg (tested ``clearance`` outside the arm's skin, by the generalised winding
number of the torso-and-legs surface), it turns the upper arm about the shoulder joint by the
smallest multiple of ``step_deg`` (found by bisection, at most ``max_angle_deg``) that takes every
such point out. Four axes are tried and the one needing the smallest turn wins: the axis along
which the points' depths push (the sum of (point - shoulder) x (way out) weighted by depth), and
turning the arm outward, forward and backward in the body's frame. The turn is stored in the
collar's frame, so it follows the body. The corrections are then spread over time (each frame
takes the largest turn within ``smooth_s`` around it, then a Gaussian of half that width) so that
the arm eases out and back instead of jumping; a second pass tops up frames that the spreading left
short where neighbouring frames needed other axes. Points near the shoulder (the armpit's skin
fold, which no pose removes) are not tested: only arm vertices farther from the shoulder joint
than ``reach_from_shoulder`` times the upper arm's length.

Several body shapes can be given: each frame's turn is built up shape by shape (each shape still
inside after the turns of those before it adds its own), so the arm clears all of them; the total
turn is capped at ``max_angle_deg`` too.
"""

from __future__ import annotations

import copy

import numpy as np

from simgen.body.model import SMPL_JOINT_NAMES, BodyModel
from simgen.body.surface import SurfaceMesh, vertex_normals
from simgen.errors import InputError
from simgen.motion.clip import MotionClip
from simgen.rotations import axis_angle_to_matrix, matrix_to_axis_angle

__all__ = ["separate_arms", "arm_torso_penetration"]

_J = {n: i for i, n in enumerate(SMPL_JOINT_NAMES)}
# (shoulder, collar, elbow, body part index of the arm in simgen.body.parts.BODY_PARTS)
_ARMS = {"left": (_J["left_shoulder"], _J["left_collar"], _J["left_elbow"], 1),
         "right": (_J["right_shoulder"], _J["right_collar"], _J["right_elbow"], 2)}
_OBSTACLE_PARTS = (0, 3, 4)  # torso, left leg, right leg


class _Obstacle:
    """Torso-and-legs surface of one posed frame (winding-number sign, Warp on the CPU)."""

    def __init__(self, vertices: np.ndarray, faces: np.ndarray):
        self.surface = SurfaceMesh(vertices, faces)

    def query(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Depth [m] of each point inside (0 outside), (P,), and the unit way out (the outward
        normal of the distance field: towards the closest surface point from inside), (P, 3)."""
        proj = self.surface.project(points)
        return np.maximum(-proj.signed_distance, 0.0), proj.normal


class _Setup:
    """Per body shape: which vertices are tested for each arm and which faces are obstacles."""

    def __init__(self, body: BodyModel, betas: np.ndarray, reach_from_shoulder: float):
        from simgen.body.parts import face_parts, vertex_parts

        self.body, self.betas = body, betas
        faces = np.asarray(body.faces, dtype=np.int64)
        fparts = face_parts(body.weights, faces)
        self.obstacle_faces = faces[np.isin(fparts, _OBSTACLE_PARTS)]
        vparts = vertex_parts(body.weights)
        rest = body.shaped_vertices(betas)[0]
        joints = body.rest_joints(betas)[0]
        self.test: dict[str, np.ndarray] = {}
        for side, (shoulder, _, elbow, part) in _ARMS.items():
            upper = np.linalg.norm(joints[elbow] - joints[shoulder])
            far = np.linalg.norm(rest - joints[shoulder], axis=1) > reach_from_shoulder * upper
            self.test[side] = np.flatnonzero((vparts == part) & far)


def _frame_state(setup: _Setup, pose: np.ndarray, trans: np.ndarray, clearance: float):
    out = setup.body.forward(betas=setup.betas, pose=pose[None], trans=trans[None])
    v = out.vertices[0]
    normals = vertex_normals(v, np.asarray(setup.body.faces, dtype=np.int64))
    obstacle = _Obstacle(v, setup.obstacle_faces)
    points = {side: v[ids] + clearance * normals[ids] for side, ids in setup.test.items()}
    return out, obstacle, points


def arm_torso_penetration(clip: MotionClip, body: BodyModel, *, betas=None, clearance: float = 0.0,
                          reach_from_shoulder: float = 0.4) -> dict[str, np.ndarray]:
    """Per frame and arm, the deepest point [m] of the arm inside the torso or a leg (0 if none).

    betas: (B',) one body shape (default zeros). Returns {"left": (T,), "right": (T,)}; points are tested ``clearance`` [m] outside the skin,
    arm vertices farther than ``reach_from_shoulder`` upper-arm lengths from the shoulder joint.
    """
    shape = body.check_betas(np.zeros(body.num_betas) if betas is None else betas)
    if shape.shape[0] != 1:
        raise InputError(f"arm_torso_penetration takes one body shape, got betas of shape {np.shape(betas)}")
    setup = _Setup(body, shape, reach_from_shoulder)
    result = {side: np.zeros(clip.num_frames) for side in _ARMS}
    for t in range(clip.num_frames):
        _, obstacle, points = _frame_state(setup, clip.poses[t], clip.trans[t], clearance)
        for side, p in points.items():
            result[side][t] = obstacle.query(p)[0].max(initial=0.0)
    return result


def _turn_needed(obstacle: _Obstacle, points: np.ndarray, shoulder: np.ndarray, elbow: np.ndarray,
                 body_axes: np.ndarray, step: float, max_angle: float) -> tuple[np.ndarray | None, float]:
    """Axis (world) and smallest angle [rad] that turn the points out of the obstacle (capped).

    Candidates: the axis along which the points' depths push, and turning the arm outward
    (abduction), forward and backward; the one that clears with the smallest angle wins.
    """
    depth, way = obstacle.query(points)
    inside = depth > 0.0
    if not inside.any():
        return None, 0.0
    arm = elbow - shoulder
    arm = arm / max(np.linalg.norm(arm), 1e-12)
    candidates = [np.sum(np.cross(points[inside] - shoulder, way[inside]) * depth[inside, None], axis=0)]
    candidates += [np.cross(arm, d) for d in body_axes]
    best_axis, best_angle = None, np.inf
    for axis in candidates:
        norm = np.linalg.norm(axis)
        if norm < 1e-9:
            continue
        axis = axis / norm

        def clears(k: int) -> bool:
            R = axis_angle_to_matrix(axis * min(k * step, max_angle))
            return not (obstacle.query(shoulder + (points - shoulder) @ R.T)[0] > 0.0).any()

        # Bisection over whole steps (the points leave the body monotonically along one turn),
        # bounded by the best angle found so far.
        hi = int(np.ceil(min(max_angle, best_angle) / step - 1e-9))
        if hi < 1 or not clears(hi):
            continue
        lo = 0
        while hi - lo > 1:
            mid = (lo + hi) // 2
            lo, hi = (lo, mid) if clears(mid) else (mid, hi)
        best_axis, best_angle = axis, min(hi * step, max_angle)
    if best_axis is None:  # nothing clears within the cap: the push axis, turned as far as allowed
        return candidates[0] / max(np.linalg.norm(candidates[0]), 1e-12), max_angle
    return best_axis, best_angle


def _search(setups, clip: MotionClip, clearance: float, step: float, max_angle: float, progress, offset: int,
            total: int) -> dict[str, np.ndarray]:
    """Per arm, the turn of each frame as a rotation vector in the collar's frame, (T, 3).

    The shapes are taken one after the other, each on the pose already turned for the ones before:
    a shape whose arms are clear by then costs one query; only a shape still inside searches, and
    its turn is added to the frame's. (Taking each shape's own turn from the unturned pose and the
    largest of them searched every shape on every frame, nine times the work for the presets.)
    """
    T = clip.num_frames
    corrections = {side: np.zeros((T, 3)) for side in _ARMS}
    for t in range(T):
        for setup in setups:
            pose = clip.poses[t].copy()
            for side, (shoulder, _, _, _) in _ARMS.items():
                c = corrections[side][t]
                if np.any(c):
                    rotation = axis_angle_to_matrix(c) @ axis_angle_to_matrix(pose[shoulder])
                    pose[shoulder] = matrix_to_axis_angle(rotation)
            out, obstacle, points = _frame_state(setup, pose, clip.trans[t], clearance)
            root = out.transforms[0, 0, :3, :3]
            for side, (shoulder, collar, elbow, _) in _ARMS.items():
                sign = 1.0 if side == "left" else -1.0
                # outward (the body's +X for the left arm), forward (+Z), backward
                body_axes = np.stack([sign * root[:, 0], root[:, 2], -root[:, 2]])
                axis, angle = _turn_needed(obstacle, points[side], out.joints[0, shoulder], out.joints[0, elbow],
                                           body_axes, step, max_angle)
                if axis is None:
                    continue
                # A world turn W about the shoulder is G_collar^T W G_collar in the collar's frame,
                # applied before the turn found so far.
                local = out.transforms[0, collar, :3, :3].T @ (axis * angle)
                turned = matrix_to_axis_angle(axis_angle_to_matrix(local)
                                              @ axis_angle_to_matrix(corrections[side][t]))
                norm = np.linalg.norm(turned)
                corrections[side][t] = turned if norm <= max_angle else turned * (max_angle / norm)
        if progress is not None:
            progress(offset + t + 1, total)
    return corrections


def _apply(clip: MotionClip, corrections: dict[str, np.ndarray]) -> MotionClip:
    poses = clip.poses.copy()
    for side, (shoulder, _, _, _) in _ARMS.items():
        c = corrections[side]
        turned = np.linalg.norm(c, axis=1) > 1e-9
        poses[turned, shoulder] = matrix_to_axis_angle(
            axis_angle_to_matrix(c[turned]) @ axis_angle_to_matrix(poses[turned, shoulder]))
    return MotionClip(clip.name, clip.fps, poses, clip.trans.copy(), clip.meta)


def separate_arms(
    clip: MotionClip,
    body: BodyModel,
    *,
    betas=None,
    clearance: float = 0.005,
    step_deg: float = 1.0,
    max_angle_deg: float = 25.0,
    smooth_s: float = 0.2,
    reach_from_shoulder: float = 0.4,
    progress=None,
) -> MotionClip:
    """The clip with each upper arm turned out of the torso and legs where it sinks in (module doc).

    body: the body the clip animates; betas: (B',) or (S, B') shapes to clear (default: zeros);
    clearance [m]: how far outside the skin the arm points are tested; step_deg, max_angle_deg: the
    search's step and cap [deg]; smooth_s [s]: width of the temporal spreading; reach_from_shoulder:
    arm vertices closer to the shoulder joint than this many upper-arm lengths are not tested.
    progress: optional callable(frames_done, frames_total). Returns a new clip whose meta records
    the operation and its per-arm largest turn [deg] and corrected frame count.
    """
    for label, value, low in (("clearance", clearance, 0.0), ("step_deg", step_deg, 1e-6),
                              ("max_angle_deg", max_angle_deg, 1e-6), ("smooth_s", smooth_s, 0.0),
                              ("reach_from_shoulder", reach_from_shoulder, 0.0)):
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not np.isfinite(value) or value < low:
            raise InputError(f"separate_arms: {label} must be a finite number >= {low:g}, got {value!r}")
    shapes = body.check_betas(np.zeros(body.num_betas) if betas is None else betas)
    setups = [_Setup(body, b[None], reach_from_shoulder) for b in shapes]
    T = clip.num_frames
    step, max_angle = np.radians(step_deg), np.radians(max_angle_deg)
    width = max(int(round(smooth_s * clip.fps / 2.0)), 0)
    # Two passes: the spread turn of one frame can fall short where its neighbours needed other
    # axes; the second pass tops those frames up (and is spread in turn).
    result, record = clip, {side: {"max_turn_deg": 0.0, "frames_turned": 0} for side in _ARMS}
    total = {side: np.zeros(T, dtype=bool) for side in _ARMS}
    for k in range(2):
        corrections = _search(setups, result, clearance, step, max_angle, progress, k * T, 2 * T)
        spread = {side: _spread(c, width) for side, c in corrections.items()}
        result = _apply(result, spread)
        for side in _ARMS:
            turned = np.linalg.norm(spread[side], axis=1) > 1e-9
            total[side] |= turned
            record[side]["max_turn_deg"] = max(record[side]["max_turn_deg"], round(float(
                np.degrees(np.linalg.norm(corrections[side], axis=1).max(initial=0.0))), 2))
            record[side]["frames_turned"] = int(total[side].sum())
    meta = copy.deepcopy(clip.meta)
    meta.setdefault("history", []).append({
        "op": "separate_arms", "clearance_m": clearance, "betas": shapes.round(6).tolist(), "step_deg": step_deg,
        "max_angle_deg": max_angle_deg, "smooth_s": smooth_s, "reach_from_shoulder": reach_from_shoulder,
        "arms": record})
    return MotionClip(clip.name, clip.fps, result.poses, clip.trans.copy(), meta)


def _spread(c: np.ndarray, width: int) -> np.ndarray:
    """Each frame takes the largest correction within +-width frames, then a Gaussian (sigma width/2)."""
    if width == 0 or not np.any(c):
        return c
    T = len(c)
    norms = np.linalg.norm(c, axis=1)
    held = np.empty_like(c)
    for t in range(T):
        lo, hi = max(0, t - width), min(T, t + width + 1)
        held[t] = c[lo + int(np.argmax(norms[lo:hi]))]
    sigma = width / 2.0
    k = np.arange(-2 * width, 2 * width + 1)
    kernel = np.exp(-0.5 * (k / sigma) ** 2)
    padded = np.concatenate([np.repeat(held[:1], 2 * width, 0), held, np.repeat(held[-1:], 2 * width, 0)])
    out = np.stack([np.convolve(padded[:, d], kernel / kernel.sum(), mode="valid") for d in range(3)], axis=1)
    return out
