"""Procedural motion library: named, deterministic clips built from smooth functions of time.

Every clip is built in three layers:

1. Root and upper body: the pelvis path, the pelvis orientation, the spine, head and arms are
   smooth functions of time (sums of sinusoids, eased keyframes, monotone cubic keyframe tracks),
   composed as rotation matrices about the body's own axes, so no Euler-angle or axis-angle
   wrap-around can make a frame jump.
2. Feet: each foot is placed on the floor by a small contact model: a ground position, a yaw, a
   pitch (toes up > 0: heel strike; heel up < 0: push-off, rolling about the ball of the foot,
   with the toes bent back so they stay flat) and a lift above the floor. Gaits place the feet from
   the pelvis path (each foot lands where the pelvis will be at its mid-stance), so a planted foot
   does not move at all while it carries weight.
3. Legs: an analytic two-bone inverse kinematics turns the pelvis and the foot targets into hip,
   knee and ankle rotations for the body at hand. The knee is a pure hinge about its rest axis
   and only bends forward; the thigh's twist follows the foot's yaw. A target the leg cannot
   reach is raised (never lowered), so a foot never goes through the floor; jumps and runs use
   that to lift the feet in a ballistic flight (g = 9.81 m/s^2), whose pelvis height is an exact
   parabola between take-off and landing.

Conventions (SMPL frame, Y-up): x is the body's left, y is up, z is forward (the body faces +z).
Each joint's local rotation acts in its parent's frame, whose axes are the world axes in the rest
pose, so the signs below read directly on the rest pose: hip flexion (thigh forward) is a negative
rotation about x, knee flexion a positive one, spine flexion (bending forward) a positive one; a
positive rotation about z raises the left arm and lowers the right one.

Arms: the rest pose is a T-pose. Every clip starts at the exact rest pose (all joint rotations
zero, feet where the rest pose has them), and the arms come down in the first ~0.9 s to a relaxed
hang of 76 deg below horizontal (about z: 14 deg at the collar, 62 deg at the shoulder, so the
hands clear the hips) with the elbows bent by 12 deg; so the simulator's ramp from the T-pose to
the first frame is empty and the garment sees the arms come down as part of the motion.

Ranges reached over the library on the open body (deg, relative to the rest pose, whose knees are
already bent by ~8): knee flexion 0..105, hip flexion -30..+105 (squat), ankle -33 (dorsiflexion)
.. +35 (plantarflexion), toes bent back up to 64 (lunge, heel high), spine flexion -8..+40 summed
over the three spine joints, elbows 0..122, only in flexion. Joint rotation speeds stay below
17 rad/s between frames at 30 fps.

Public API: :data:`PROCEDURAL_CLIPS`, :func:`make_clip`, :func:`list_procedural`.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

import numpy as np
from scipy.interpolate import CubicHermiteSpline, CubicSpline, PchipInterpolator

from simgen.body.model import BodyModel
from simgen.errors import InputError
from simgen.motion.clip import MotionClip
from simgen.rotations import (
    axis_angle_to_matrix,
    axis_angle_to_quat,
    matrix_to_axis_angle,
    matrix_to_quat,
    quat_slerp,
    quat_to_matrix,
)

__all__ = ["PROCEDURAL_CLIPS", "make_clip", "list_procedural", "GRAVITY"]

#: Gravity used for ballistic flight phases [m/s^2].
GRAVITY = 9.81
#: [Hz] the grid on which a clip's pelvis height is computed where it filters over time
HEIGHT_RATE = 240.0

# SMPL joint indices used here.
_PELVIS, _L_HIP, _R_HIP, _SPINE1, _L_KNEE, _R_KNEE, _SPINE2, _L_ANKLE, _R_ANKLE, _SPINE3 = range(10)
_L_FOOT, _R_FOOT, _NECK, _L_COLLAR, _R_COLLAR, _HEAD, _L_SHOULDER, _R_SHOULDER = range(10, 18)
_L_ELBOW, _R_ELBOW = 18, 19

_DEG = np.pi / 180.0
_MIRROR = np.diag([-1.0, 1.0, 1.0])

#: Relaxed arm hang below horizontal [rad] and the collar's share of any arm elevation.
RELAXED_ARM = 76.0 * _DEG
_COLLAR_SHARE = 0.18
_RELAXED_ELBOW = 12.0 * _DEG
#: Time over which the arms come down from the T-pose at the start of every clip [s].
_ARMS_DOWN_TIME = 0.9


# ---------------------------------------------------------------------------------------------
# Smooth building blocks
# ---------------------------------------------------------------------------------------------
def _smoothstep(x):
    """Quintic smoothstep on [0, 1] (zero first and second derivatives at both ends), clamped."""
    x = np.clip(x, 0.0, 1.0)
    return x * x * x * (10.0 + x * (-15.0 + 6.0 * x))


def _ease(t, t0, t1):
    """0 before t0, 1 after t1, quintic in between."""
    return _smoothstep((np.asarray(t, dtype=np.float64) - t0) / (t1 - t0))


def _track(t, keys):
    """Monotone cubic (PCHIP) keyframe track through keys [(time [s], value), ...], held at the ends.

    PCHIP is C1, never overshoots between keys, and has zero slope at every local extremum and on
    runs of equal values, so a key that is a turning point is passed at zero velocity while keys
    on a monotone run are passed without stopping. Repeat a value to hold it.
    """
    times = np.array([k[0] for k in keys], dtype=np.float64)
    values = np.array([k[1] for k in keys], dtype=np.float64)
    t = np.asarray(t, dtype=np.float64)
    if len(times) == 1:
        return np.full(t.shape + values.shape[1:], values[0])
    # Extra keys beyond each end make the end slopes zero (a clip starts and ends at rest).
    times = np.concatenate([[times[0] - 1.0], times, [times[-1] + 1.0]])
    values = np.concatenate([values[:1], values, values[-1:]])
    return PchipInterpolator(times, values, axis=0)(np.clip(t, times[1], times[-2]))


def _bump(tau, peak=0.5):
    """A lift profile on tau in [0, 1]: 0 with zero slope at both ends, 1 at tau = peak (0.3..0.7)."""
    tau = np.clip(tau, 0.0, 1.0)
    k = np.log(0.5) / np.log(peak)  # maps peak -> 1/2
    return np.sin(np.pi * tau**k) ** 2


def _huber_relu(x, eps):
    """0 for x <= 0, x^2 / (2 eps) on (0, eps), x - eps / 2 beyond: a C1 ramp."""
    x = np.asarray(x, dtype=np.float64)
    return np.where(x <= 0.0, 0.0, np.where(x < eps, x * x / (2.0 * eps), x - 0.5 * eps))


def _softplus(x, eps):
    """eps log(1 + exp(x / eps)) - eps log 2: smooth max(x, 0) shifted so that it is 0 at x = 0."""
    x = np.asarray(x, dtype=np.float64)
    return eps * (np.logaddexp(0.0, x / eps) - np.log(2.0))


def _rot(axis: int, angle) -> np.ndarray:
    """Rotations about a coordinate axis (0 = x, 1 = y, 2 = z) by angle [rad], shape (T,) -> (T, 3, 3)."""
    angle = np.atleast_1d(np.asarray(angle, dtype=np.float64))
    aa = np.zeros(angle.shape + (3,))
    aa[..., axis] = angle
    return axis_angle_to_matrix(aa)


def _rx(a):
    return _rot(0, a)


def _ry(a):
    return _rot(1, a)


def _rz(a):
    return _rot(2, a)


def _mirror_rot(R):
    """Left-right mirror of rotations: M R M with M = diag(-1, 1, 1)."""
    return _MIRROR @ R @ _MIRROR


# ---------------------------------------------------------------------------------------------
# Upper-body helpers (local rotation matrices, shape (T, 3, 3))
# ---------------------------------------------------------------------------------------------
def _arm(t, *, elev, swing=0.0, plane=0.0, twist=0.0, elbow=0.0, left=True):
    """Collar, shoulder and elbow rotations of one arm, as a dict joint -> (T, 3, 3).

    All angles [rad], arrays of shape (T,) or scalars, written for the left arm and mirrored for the
    right one: elev raises the arm in the frontal plane (0 = T-pose, -RELAXED_ARM = hanging relaxed,
    +pi/2 = straight up); swing then turns it forward about the body's left-right axis (arm
    swing in walking, forward raise); plane turns it about the vertical axis (+ towards the
    front: horizontal adduction); twist rotates the upper arm about its own axis (+ turns a bent
    forearm inwards); elbow flexes the forearm (>= 0 only: the elbow bends one way). The collar
    takes _COLLAR_SHARE of the elevation, as the shoulder girdle does; wrists stay in line.
    """
    f = lambda a: np.broadcast_to(np.asarray(a, dtype=np.float64), np.shape(t))  # noqa: E731
    elev, swing, plane, twist, elbow = map(f, (elev, swing, plane, twist, elbow))
    collar = _rz(_COLLAR_SHARE * elev)
    shoulder = _ry(-plane) @ _rx(-swing) @ _rz((1.0 - _COLLAR_SHARE) * elev) @ _rx(twist)
    rots = {"collar": collar, "shoulder": shoulder, "elbow": _ry(-np.maximum(elbow, 0.0))}
    if left:
        joints = {"collar": _L_COLLAR, "shoulder": _L_SHOULDER, "elbow": _L_ELBOW}
        return {joints[k]: v for k, v in rots.items()}
    joints = {"collar": _R_COLLAR, "shoulder": _R_SHOULDER, "elbow": _R_ELBOW}
    return {joints[k]: _mirror_rot(v) for k, v in rots.items()}


def _arms_down(t, until=_ARMS_DOWN_TIME):
    """Weight 0 -> 1 over [0, until]: the arms coming down from the T-pose."""
    return _ease(t, 0.0, until)


def _relaxed_arms(t, *, swing_l=0.0, swing_r=0.0, elbow_l=0.0, elbow_r=0.0, extra_elev_l=0.0,
                  extra_elev_r=0.0):
    """Both arms lowered from the T-pose to the relaxed hang, plus optional swings and elbow flexion."""
    down = _arms_down(t)
    rots = _arm(t, elev=-RELAXED_ARM * down + extra_elev_l, swing=swing_l, elbow=_RELAXED_ELBOW * down + elbow_l,
                left=True)
    rots.update(_arm(t, elev=-RELAXED_ARM * down + extra_elev_r, swing=swing_r,
                     elbow=_RELAXED_ELBOW * down + elbow_r, left=False))
    return rots


def _spine(t, *, flex=0.0, side=0.0, twist=0.0, weights=(0.35, 0.35, 0.30)):
    """spine1..3 rotations sharing a trunk motion [rad]: flex > 0 bends forward, side > 0 bends
    towards the body's left, twist > 0 turns the chest towards the left."""
    f = lambda a: np.broadcast_to(np.asarray(a, dtype=np.float64), np.shape(t))  # noqa: E731
    flex, side, twist = map(f, (flex, side, twist))
    return {j: _ry(w * twist) @ _rx(w * flex) @ _rz(-w * side)
            for j, w in zip((_SPINE1, _SPINE2, _SPINE3), weights)}


def _head(t, *, flex=0.0, side=0.0, twist=0.0):
    """neck and head rotations sharing a head motion [rad] (same signs as _spine)."""
    return {j: r for j, r in zip((_NECK, _HEAD), _spine(t, flex=flex, side=side, twist=twist,
                                                          weights=(0.5, 0.5, 0.0)).values())}


def _root_rot(t, *, yaw=0.0, tilt=0.0, roll=0.0):
    """Pelvis orientation: yaw > 0 turns towards the body's left, tilt > 0 tips forward, roll > 0
    leans the upper body towards the left. Shape (T, 3, 3)."""
    f = lambda a: np.broadcast_to(np.asarray(a, dtype=np.float64), np.shape(t))  # noqa: E731
    yaw, tilt, roll = map(f, (yaw, tilt, roll))
    return _ry(yaw) @ _rx(tilt) @ _rz(-roll)


# ---------------------------------------------------------------------------------------------
# The rig: leg geometry of a body, foot contact model and two-bone IK
# ---------------------------------------------------------------------------------------------
@dataclass
class _Foot:
    """One foot's contact state over time.

    ground [m], shape (T, 3): where the point under the rest ankle is (y = 0 on the floor);
    yaw [rad], shape (T,): heading of the foot (+ turns the toes towards the body's left);
    pitch [rad], shape (T,): + toes up (rolling on the heel), - heel up (rolling on the ball);
    lift [m], shape (T,): height of the whole foot above that contact;
    relax, shape (T,) or None: weight in [0, 1] with which the ankle, while the foot is in the air,
    turns from the contact model's orientation to relax_angle [rad] of plantarflexion relative to
    the shin (a swinging foot follows its shin instead of staying level with the floor).
    """

    ground: np.ndarray
    yaw: np.ndarray
    pitch: np.ndarray
    lift: np.ndarray
    relax: np.ndarray | None = None
    relax_angle: float = 0.0


@dataclass
class _Spec:
    """What a clip builder returns: root path and orientation, upper-body rotations, feet."""

    t: np.ndarray
    root_pos: np.ndarray  # world position of the pelvis joint [m], (T, 3), floor at y = 0
    root_rot: np.ndarray  # (T, 3, 3)
    local: dict = field(default_factory=dict)  # joint -> (T, 3, 3) for non-leg joints
    feet: tuple = ()  # (_Foot left, _Foot right)
    # Fraction of the rest hip-ankle distance (scalar or (T,)) at which an out-of-reach foot hangs.
    hang_reach: float | np.ndarray = 1.0
    # The pelvis height depends on neighbouring times (a filter over samples): the builder takes it
    # from the spec evaluated on a fixed grid of HEIGHT_RATE, so a clip is the same at every fps.
    height_from_grid: bool = False


class _Rig:
    """Leg geometry of a body of shape betas, shifted so that the rest soles are at y = 0."""

    _PIVOT_BLEND = 0.04  # [rad] pitch band over which the rolling pivot moves from heel to ball

    def __init__(self, body: BodyModel, betas=None):
        v = body.shaped_vertices(np.zeros(body.num_betas) if betas is None else betas)[0]
        J = body.J_regressor @ v
        w = body.weights
        sides = ((_L_HIP, _L_KNEE, _L_ANKLE, _L_FOOT), (_R_HIP, _R_KNEE, _R_ANKLE, _R_FOOT))
        foot_mask = [(w[:, a] + w[:, f]) >= 0.5 for _, _, a, f in sides]
        if not all(np.count_nonzero(m) >= 4 for m in foot_mask):
            raise InputError(f"body model {body.name!r}: no vertices are skinned to the ankles and feet")
        self.sole = float(min(v[m, 1].min() for m in foot_mask))
        self.J = J - np.array([0.0, self.sole, 0.0])
        self.J_offset = J[0] - self.J[0]  # model rest pelvis minus rig rest pelvis
        vs = v - np.array([0.0, self.sole, 0.0])
        self.legs = []
        for (hip, knee, ankle, foot), mask in zip(sides, foot_mask):
            H0, K0, A0, B0 = self.J[hip], self.J[knee], self.J[ankle], self.J[foot]
            pts = vs[mask]
            sole_pts = pts[pts[:, 1] < 0.015]
            heel = np.array([A0[0], 0.0, sole_pts[:, 2].min()])
            # Push-off rolls about a point halfway between the ball joint and the floor: the
            # metatarsal heads roll between the two, and the sole under the ball and the toes then
            # shift by half the joint height times the heel-up angle's sine (< 1 cm), not twice that.
            ball = np.array([B0[0], 0.5 * B0[1], B0[2]])
            d0 = A0 - H0
            D0 = float(np.linalg.norm(d0))
            F0 = self._frame(d0[None], np.array([[0.0, 0.0, 1.0]]))[0]
            tc = F0.T @ (K0 - H0)
            sc = F0.T @ (A0 - K0)
            t2, s2 = tc[:2], sc[:2]
            phi0 = float(np.arctan2(t2[0] * s2[1] - t2[1] * s2[0], t2 @ s2))
            self.legs.append(dict(
                hip=hip, knee=knee, ankle=ankle, foot=foot, H0=H0, A0=A0, ball=ball, heel=heel,
                ground0=np.array([A0[0], 0.0, A0[2]]), D0=D0, F0=F0, t2=t2, s2=s2,
                a=float(np.linalg.norm(t2)), b=float(np.linalg.norm(s2)), phi0=phi0,
            ))
        self.pelvis_height = float(self.J[0, 1])

    # -- geometry helpers ------------------------------------------------------------------
    @staticmethod
    def _frame(d, hint):
        """Orthonormal frames [d, hint orthogonalised, d x hint] as columns, shape (T, 3, 3)."""
        e1 = d / np.linalg.norm(d, axis=-1, keepdims=True)
        k = hint - np.sum(hint * e1, axis=-1, keepdims=True) * e1
        e2 = k / np.linalg.norm(k, axis=-1, keepdims=True)
        e3 = np.cross(e1, e2)
        return np.stack([e1, e2, e3], axis=-1)

    def foot_rotation(self, foot: _Foot):
        """Global foot orientation (T, 3, 3): yaw about y after pitch about x (+ toes up)."""
        return _ry(foot.yaw) @ _rx(-foot.pitch)

    def ankle_target(self, side: int, foot: _Foot):
        """World ankle position [m], shape (T, 3), for a foot state: the foot rolls about its heel
        (pitch > 0) or about the ball joint (pitch < 0), blended over a small band so the
        trajectory stays C1 where the pitch changes sign."""
        leg = self.legs[side]
        wheel = _smoothstep((foot.pitch + self._PIVOT_BLEND) / (2.0 * self._PIVOT_BLEND))[:, None]
        pivot = leg["ball"] + wheel * (leg["heel"] - leg["ball"])  # rest position of the pivot, (T, 3)
        Ry = _ry(foot.yaw)
        Rp = _rx(-foot.pitch)
        rolled = np.einsum("tab,tb->ta", Rp, leg["A0"] - pivot) + pivot - leg["ground0"]
        A = foot.ground + np.einsum("tab,tb->ta", Ry, rolled)
        A[:, 1] += foot.lift
        return A

    def hip_position(self, side: int, root_pos, root_rot):
        """World hip joint position [m], shape (T, 3)."""
        return root_pos + np.einsum("tab,b->ta", root_rot, self.legs[side]["H0"] - self.J[0])

    def reach_height(self, side: int, root_xz, root_rot, ankle, reach=0.997):
        """Highest pelvis height [m], shape (T,), at which the hip is within reach (a fraction of the
        rest hip-ankle distance, scalar or (T,)) of the ankle target [m], (T, 3); root_xz: pelvis x
        and z [m], (T, 2); root_rot: pelvis orientation, (T, 3, 3)."""
        leg = self.legs[side]
        off = np.einsum("tab,b->ta", root_rot, leg["H0"] - self.J[0])
        dx = root_xz[:, 0] + off[:, 0] - ankle[:, 0]
        dz = root_xz[:, 1] + off[:, 2] - ankle[:, 2]
        r = reach * leg["D0"]
        return ankle[:, 1] + np.sqrt(np.maximum(r * r - dx * dx - dz * dz, 0.0)) - off[:, 1]

    def leg_ik(self, side: int, H, A, hint):
        """Two-bone IK. H, A: hip and ankle target [m], (T, 3); hint: knee direction, (T, 3).

        Returns the hip's global rotation (T, 3, 3) and the knee's local rotation (T, 3, 3). The
        rest leg is reproduced exactly when A - H equals its rest value; targets beyond the rest
        hip-ankle distance have been raised by the caller, and are clamped here.
        """
        leg = self.legs[side]
        d = A - H
        D = np.linalg.norm(d, axis=-1)
        # Law of cosines in the leg's plane: the hinge rotations keep the rest knee's small offset
        # out of that plane, so thigh and shin act with their in-plane lengths a and b. Targets
        # the caller could not bring within reach are clamped to the straightest rest leg.
        a, b = leg["a"], leg["b"]
        D = np.minimum(D, min(leg["D0"], a + b))
        c = np.clip((D * D - a * a - b * b) / (2.0 * a * b), -1.0, 1.0)
        # Knees flexed forward have phi < 0 (the signed angle from thigh to shin in the
        # (hip->ankle, knee hint) plane). For a rest knee that is bent (phi0 < 0) the rest target
        # gives gamma = 0 exactly; a slightly over-straight rest knee (phi0 > 0) starts 2 phi0 off.
        phi = -np.arccos(c)
        gamma = phi - leg["phi0"]
        cg, sg = np.cos(gamma), np.sin(gamma)
        s2 = leg["s2"]
        w1 = leg["t2"][0] + cg * s2[0] - sg * s2[1]
        w2 = leg["t2"][1] + sg * s2[0] + cg * s2[1]
        beta = -np.arctan2(w2, w1)
        # Both rotations turn about the third axis of the leg frames [hip->ankle, knee hint, normal]
        # (in frame coordinates that is a rotation about z): the hip swings the rest leg into the
        # target frame, the knee is a hinge about the rest leg's normal.
        F = self._frame(d, hint)
        F0 = leg["F0"]
        G_hip = F @ _rz(beta) @ F0.T
        knee_local = F0 @ _rz(gamma) @ F0.T
        return G_hip, knee_local


def _solve(rig: _Rig, spec: _Spec):
    """Turn a clip spec into SMPL poses (T, 24, 3) and root translations (T, 3) for the rig's body."""
    T = spec.t.shape[0]
    R = np.broadcast_to(np.eye(3), (T, 24, 3, 3)).copy()
    for j, m in spec.local.items():
        R[:, j] = m
    R[:, _PELVIS] = spec.root_rot
    for side, foot in enumerate(spec.feet):
        leg = rig.legs[side]
        A = rig.ankle_target(side, foot)
        H = rig.hip_position(side, spec.root_pos, spec.root_rot)
        # Raise a target the leg cannot reach (never lower it): feet hang from the hip in flight,
        # with the knee as bent as the clip's contacts have it (hang_reach), so touch-down is smooth.
        dx, dz = H[:, 0] - A[:, 0], H[:, 2] - A[:, 2]
        r = spec.hang_reach * leg["D0"]
        room = np.sqrt(np.maximum(r * r - dx * dx - dz * dz, 0.0))
        A[:, 1] += _huber_relu(H[:, 1] - A[:, 1] - room, 0.01)
        hint = np.stack([np.sin(foot.yaw), np.zeros(T), np.cos(foot.yaw)], axis=-1)
        G_hip, knee_local = rig.leg_ik(side, H, A, hint)
        R[:, leg["hip"]] = np.swapaxes(spec.root_rot, -1, -2) @ G_hip
        R[:, leg["knee"]] = knee_local
        G_knee = G_hip @ knee_local
        ankle = np.swapaxes(G_knee, -1, -2) @ rig.foot_rotation(foot)
        # Toes bend back as the heel rises so that they stay flat on the floor.
        toes = _softplus(-foot.pitch, 0.03)
        if foot.relax is not None:
            w = np.clip(foot.relax, 0.0, 1.0)
            q = quat_slerp(matrix_to_quat(ankle), axis_angle_to_quat(np.array([foot.relax_angle, 0.0, 0.0])), w)
            ankle = quat_to_matrix(q)
            toes = toes * (1.0 - w)
        R[:, leg["ankle"]] = ankle
        R[:, leg["foot"]] = _rx(-toes)
    poses = matrix_to_axis_angle(R)
    # SMPL's translation moves the model's own rest pelvis (the rig's is shifted to the floor).
    trans = spec.root_pos - (rig.J[0] + rig.J_offset)
    return poses, trans


# ---------------------------------------------------------------------------------------------
# Trajectory helpers
# ---------------------------------------------------------------------------------------------
def _hermite(t, keys):
    """Piecewise cubic Hermite through keys [(time [s], value, slope [1/s]), ...], held at the ends.

    A piece whose end keys lie on one parabola of curvature -g (a take-off and a landing computed
    with :func:`_flight`) is exactly that parabola, so ballistic phases are exact.
    """
    times = np.array([k[0] for k in keys], dtype=np.float64)
    values = np.array([k[1] for k in keys], dtype=np.float64)
    slopes = np.array([k[2] for k in keys], dtype=np.float64)
    t = np.asarray(t, dtype=np.float64)
    out = CubicHermiteSpline(times, values, slopes)(np.clip(t, times[0], times[-1]))
    # Outside the keys: continue linearly with the end slope (zero for a clip at rest).
    out = out + np.where(t < times[0], (t - times[0]) * slopes[0], 0.0)
    return out + np.where(t > times[-1], (t - times[-1]) * slopes[-1], 0.0)


def _flight(y0, y1, duration):
    """Ballistic flight from height y0 to y1 [m] in duration [s]: (take-off, landing) vertical speeds."""
    v0 = (y1 - y0) / duration + 0.5 * GRAVITY * duration
    return v0, v0 - GRAVITY * duration


def _path_from_velocity(t_end, speed, heading, *, direction=0.0, start=(0.0, 0.0)):
    """Ground path of the pelvis (x, z) [m] from speed(t) [m/s] and a travel direction heading(t) +
    direction [rad] (0 = +z, the body's front at rest). Returns a function t -> (N, 2)."""
    grid = np.arange(-2.0, t_end + 2.0, 1e-3)
    v = speed(grid)
    psi = heading(grid) + direction
    vx, vz = v * np.sin(psi), v * np.cos(psi)
    x = np.concatenate([[0.0], np.cumsum(0.5 * (vx[1:] + vx[:-1]) * 1e-3)])
    z = np.concatenate([[0.0], np.cumsum(0.5 * (vz[1:] + vz[:-1]) * 1e-3)])
    x += start[0] - np.interp(0.0, grid, x)
    z += start[1] - np.interp(0.0, grid, z)
    return lambda s: np.stack([np.interp(s, grid, x), np.interp(s, grid, z)], axis=-1)


@dataclass
class _Gait:
    """Parameters of a periodic gait (walk, run, side step, turn).

    cadence [cycles/s] (one cycle = two steps); duty: fraction of a cycle a foot is on the floor at
    full gait (> 0.5 walks with double support, < 0.5 runs with a flight phase); duty0: the same at
    rest (the gait fades in from standing); half_width [m]: lateral distance of each foot from the
    pelvis path (None keeps the rest stance); toe_out [rad]; lift [m]: ankle lift in swing, peaking
    at lift_peak of the swing; strike, push [rad]: toes up at touch-down and heel up at lift-off;
    flat: fractions of the stance where the foot becomes flat and where the heel leaves the floor;
    swing_ankle [rad]: plantarflexion relative to the shin that the foot turns to in mid-swing (None:
    the foot stays level, for short shuffling steps whose toes would otherwise brush the floor);
    travel_delay: fraction of the swing at each end during which the foot only rises / descends.
    """

    cadence: float
    duty: float
    lift: float
    duty0: float | None = None
    half_width: float | None = None
    toe_out: float = 0.0
    lift_peak: float = 0.4
    strike: float = 0.0
    push: float = 0.0
    flat: tuple = (0.2, 0.55)
    swing_ankle: float | None = 0.0
    travel_delay: float = 0.0


class _GaitPlan:
    """Footsteps of a gait along a pelvis path: each foot lands where the pelvis will be at the
    middle of its stance (plus the lateral offset), so a planted foot never slides.

    env(t) in [0, 1] fades the gait in (0 = standing still in the rest stance); path(t) -> (N, 2)
    pelvis ground path (x, z); heading(t) -> (N,) body heading [rad].
    """

    def __init__(self, rig: _Rig, t_end: float, gait: _Gait, env: Callable, path: Callable, heading: Callable):
        self.g = gait
        c = gait.cadence
        duty0 = gait.duty if gait.duty0 is None else gait.duty0
        n_max = int(np.ceil(t_end * c)) + 3
        self.stances = []  # per side: dict of arrays over steps k
        for side, offset in enumerate((0.0, 0.5)):
            leg = rig.legs[side]
            sign = 1.0 if side == 0 else -1.0
            td = (np.arange(-1, n_max) + offset) / c
            duty = duty0 + (gait.duty - duty0) * env(td)
            lo = td + duty / c
            mid = 0.5 * (td + lo)
            e_mid = env(mid)
            psi = heading(mid)
            rest_lat = leg["ground0"][0] - rig.J[0, 0]
            lat = rest_lat if gait.half_width is None else rest_lat + (sign * gait.half_width - rest_lat) * e_mid
            lon = leg["ground0"][2] - rig.J[0, 2]
            P = path(mid)
            gx = P[:, 0] + np.cos(psi) * lat + np.sin(psi) * lon
            gz = P[:, 1] - np.sin(psi) * lat + np.cos(psi) * lon
            self.stances.append(dict(td=td, lo=lo, mid=mid, ground=np.stack([gx, np.zeros_like(gx), gz], -1),
                                     yaw=psi + sign * gait.toe_out * e_mid, e_mid=e_mid,
                                     e_td=env(td), e_lo=env(lo)))

    def phase(self, t):
        """Gait phase [cycles]: the left foot touches down at integers, the right at half-integers."""
        return self.g.cadence * np.asarray(t, dtype=np.float64)

    def contact_events(self):
        """All stances of both feet as (touch-down time, lift-off time, side), sorted by time."""
        ev = [(td, lo, side) for side, st in enumerate(self.stances) for td, lo in zip(st["td"], st["lo"])]
        return sorted(ev)

    def feet(self, t):
        """Foot states (left, right) at times t [s], shape (T,)."""
        t = np.asarray(t, dtype=np.float64)
        g = self.g
        out = []
        for st in self.stances:
            k = np.clip(np.searchsorted(st["td"], t, side="right") - 1, 0, len(st["td"]) - 2)
            in_swing = t >= st["lo"][k]
            tau = np.where(in_swing, (t - st["lo"][k]) / (st["td"][k + 1] - st["lo"][k]), 0.0)
            # A cubic ease: C1 with zero velocity at lift-off and touch-down and a peak foot speed
            # of 1.5x the mean (a quintic's 1.9x makes the knee snap straight before landing).
            # Low shuffling steps travel only between travel_delay and 1 - travel_delay of the
            # swing, so the foot clears the floor before it moves and stops before it lands.
            d = g.travel_delay
            u = np.clip((tau - d) / (1.0 - 2.0 * d), 0.0, 1.0)
            s = (u * u * (3.0 - 2.0 * u))[:, None]
            ground = st["ground"][k] + s * (st["ground"][k + 1] - st["ground"][k])
            yaw = st["yaw"][k] + s[:, 0] * (st["yaw"][k + 1] - st["yaw"][k])
            # The lift follows the gait amplitude of the stances on either side of the swing, so a
            # foot that moves (into or out of the gait's stance) is always lifted, never dragged.
            e_swing = np.maximum(st["e_mid"][k], st["e_mid"][k + 1])
            lift = np.where(in_swing, g.lift * e_swing * _bump(tau, g.lift_peak), 0.0)
            keys = []
            for td, lo, e_td, e_lo in zip(st["td"], st["lo"], st["e_td"], st["e_lo"]):
                dur = lo - td
                keys += [(td, g.strike * e_td), (td + g.flat[0] * dur, 0.0), (td + g.flat[1] * dur, 0.0),
                         (lo, -g.push * e_lo)]
            pitch = _track(t, keys)
            relax = None if g.swing_ankle is None else np.where(in_swing, e_swing * np.sin(np.pi * tau) ** 2, 0.0)
            out.append(_Foot(ground=ground, yaw=yaw, pitch=pitch, lift=lift, relax=relax,
                             relax_angle=g.swing_ankle or 0.0))
        return tuple(out)


def _still_foot(rig: _Rig, side: int, t) -> _Foot:
    """A foot standing where the rest pose has it."""
    T = np.shape(t)[0]
    return _Foot(ground=np.tile(rig.legs[side]["ground0"], (T, 1)), yaw=np.zeros(T), pitch=np.zeros(T),
                 lift=np.zeros(T))


def _moved_foot(rig: _Rig, side: int, t, *, steps=(), pitch=None, yaw=None, ground=None) -> _Foot:
    """A foot moved by discrete steps from its rest place.

    steps: [(t0, t1, dx, dz, lift), ...]: between t0 and t1 [s] the foot moves by (dx, dz) [m] along
    the floor, eased, while lifted by up to lift [m] (a bump peaking at mid-step). pitch / yaw:
    optional (T,) tracks [rad]; ground: optional extra (T, 3) ground offset.
    """
    t = np.asarray(t, dtype=np.float64)
    T = t.shape[0]
    g = np.tile(rig.legs[side]["ground0"], (T, 1))
    lift = np.zeros(T)
    for t0, t1, dx, dz, h in steps:
        s = _ease(t, t0, t1)
        g[:, 0] += dx * s
        g[:, 2] += dz * s
        lift += h * _bump((t - t0) / (t1 - t0), 0.5)
    if ground is not None:
        g = g + ground
    return _Foot(ground=g, yaw=np.zeros(T) if yaw is None else yaw, pitch=np.zeros(T) if pitch is None else pitch,
                 lift=lift)


def _fit_height(rig: _Rig, t, nominal, root_xz, root_rot, feet, env, *, reach=0.997, window=0.2):
    """Pelvis height [m], shape (T,): the nominal height, lowered wherever a foot target would
    otherwise be out of reach (so planted feet stay planted and the knees keep a little flexion),
    by a smooth envelope of what the feet need rather than the need itself.

    The need d(t) = max(nominal - reach height, 0) rises as fast as a foot moves away, and following
    it can drop the pelvis faster than gravity could (BENCHMARKS.md, "Procedural clips"). Here
    d is first widened to its running maximum over +-``window`` [s] and then averaged with a
    Gaussian truncated at that window: the average of values that each are at least d(t) is at
    least d(t), so the feet stay in reach, and the pelvis starts down before the foot needs it.
    env in [0, 1] fades the constraint and the early start in, so a clip at rest keeps the rest
    height.
    t: times [s], shape (T,), evenly spaced."""
    from scipy.ndimage import maximum_filter1d

    nominal = np.asarray(nominal, dtype=np.float64)
    r = 1.0 - (1.0 - reach) * np.asarray(env, dtype=np.float64)
    limit = np.min([rig.reach_height(side, root_xz, root_rot, rig.ankle_target(side, foot), reach=r)
                    for side, foot in enumerate(feet)], axis=0)
    need = np.maximum(nominal - limit, 0.0)
    if len(t) < 2 or not need.any():
        return nominal - need
    w = max(1, int(round(window / float(t[1] - t[0]))))
    wide = maximum_filter1d(need, size=2 * w + 1, mode="nearest")
    kernel = np.exp(-0.5 * (np.arange(-w, w + 1) / (0.5 * w)) ** 2)
    smooth = np.convolve(np.pad(wide, w, mode="edge"), kernel / kernel.sum(), mode="valid")
    # the early start fades in with env like the need itself, so frame 0 stays the rest pose
    return nominal - np.maximum(np.asarray(env, dtype=np.float64) * smooth, need)


def _walk_height(rig: _Rig, t, plan: "_GaitPlan", root_xz_at, root_rot_at, env, nominal_at, *, reach=0.997,
                 rate=HEIGHT_RATE, margin=0.001) -> np.ndarray:
    """Pelvis height of a walk [m], shape (T,): the nominal height (with its bob) minus one smooth
    dip per double support, as deep as the feet need there, so the pelvis is lowest while both feet
    are down and moves with the gait's rhythm.

    The reach limit alone follows the landing foot's descent, so the pelvis would drop within a
    frame or two at each heel strike. Here the limit is sampled at
    ``rate`` [Hz]; a cubic with flat keys at the limit's lowest point between each two mid-stances
    (one per double support) and halfway between those goes down to the limit there, and each key
    is deepened by what still sticks out near it until the curve stays ``margin`` [m] (faded in with
    the gait) under the limit; the plain minimum with the limit guards what is left."""
    # a step beyond each end, so that the first and last dips are shaped like the others
    pad = 1.0 / plan.g.cadence
    grid = np.arange(float(t[0]) - pad, float(t[-1]) + pad, 1.0 / rate)

    def limit(s):
        e = env(s)
        r = 1.0 - (1.0 - reach) * e
        xz, rot, feet = root_xz_at(s), root_rot_at(s), plan.feet(s)
        return np.min([rig.reach_height(side, xz, rot, rig.ankle_target(side, foot), reach=r)
                       for side, foot in enumerate(feet)], axis=0)

    nominal, lim = nominal_at(grid), limit(grid)
    slack = margin * env(grid)  # none at rest, where the limit is the rest height itself
    deficit = nominal - lim + slack
    mids = np.sort(np.concatenate([st["mid"] for st in plan.stances]))
    bounds = np.concatenate([[grid[0]], mids[(mids > grid[0]) & (mids < grid[-1])], [grid[-1]]])
    seg = np.clip(np.searchsorted(bounds, grid, side="right") - 1, 0, len(bounds) - 2)
    lows = np.array([np.flatnonzero(seg == k)[np.argmax(deficit[seg == k])] for k in range(len(bounds) - 1)])
    # keys: each double support's deepest point, the highs halfway between them, and the ends
    highs = (lows[1:] + lows[:-1]) // 2
    idx = np.unique(np.concatenate([[0, len(grid) - 1], lows, highs]))
    depth = np.maximum(deficit[idx], 0.0)
    nearest = np.abs(grid[:, None] - grid[idx][None, :]).argmin(axis=1)

    def dip(s):
        return _hermite(s, [(float(grid[i]), -float(d), 0.0) for i, d in zip(idx, depth)])

    for _ in range(8):  # deepen each key by what still sticks out of the limit nearest to it
        over = deficit + dip(grid)
        extra = np.zeros(len(idx))
        np.maximum.at(extra, nearest, over)
        if extra.max() < 1e-5:
            break
        depth += extra
    y = nominal_at(t) + dip(t)
    return np.minimum(y, limit(t))


def _integral(fn: Callable, t_end: float) -> Callable:
    """Antiderivative of fn (zero at t = 0) as a function of time, from a 1 ms trapezoid grid."""
    grid = np.arange(-2.0, t_end + 2.0, 1e-3)
    y = fn(grid)
    F = np.concatenate([[0.0], np.cumsum(0.5 * (y[1:] + y[:-1]) * 1e-3)])
    F -= np.interp(0.0, grid, F)
    return lambda s: np.interp(s, grid, F)


# ---------------------------------------------------------------------------------------------
# Clip builders. Each takes the rig and the frame times t [s], shape (T,), and returns a _Spec.
# ---------------------------------------------------------------------------------------------
def _gait_clip(rig: _Rig, t, gait: _Gait, *, speed: float, ramp=(0.45, 2.2), heading=None, direction=0.0,
               run=False, drop=0.015, bob=0.012, sway=0.02, pelvis_yaw=5 * _DEG, pelvis_roll=3 * _DEG,
               lean=0.0, arm_swing=18 * _DEG, elbow=8 * _DEG, elbow_swing=14 * _DEG, arm_lift=0.0,
               speed_fn=None, env=None, run_drop=0.06, run_reach=0.975) -> _Spec:
    """A periodic gait along a path: walk, fast walk, curved walk, run, side step, turn in place.

    speed [m/s] (or speed_fn(t)) fades in with env(t) (default: eased over ramp [s]), which also
    scales every gait amplitude (0 = standing in the rest stance); heading(t) [rad] turns the body;
    direction [rad] is the travel direction relative to the heading (pi/2: sideways to the left).
    Walks keep the pelvis at a nominal height with a double-frequency bob, lowered where a foot
    target needs it; runs alternate stance (a cubic that compresses the leg) and an exact
    ballistic flight between take-off and landing.
    """
    T_end = float(t[-1])
    env = env or (lambda s: _ease(s, *ramp))
    heading = heading or (lambda s: np.zeros(np.shape(s)))
    vel = speed_fn or (lambda s: speed * env(s))
    path = _path_from_velocity(T_end, vel, heading, direction=direction, start=(rig.J[0, 0], rig.J[0, 2]))
    plan = _GaitPlan(rig, T_end, gait, env, path, heading)
    D = gait.duty
    Y0 = rig.pelvis_height

    def root_rot_at(s):
        e, phi = env(s), plan.phase(s)
        return _root_rot(s, yaw=heading(s) - pelvis_yaw * e * np.cos(2 * np.pi * phi),
                         tilt=0.4 * lean * e, roll=-pelvis_roll * e * np.cos(2 * np.pi * (phi - D / 2)))

    def root_xz_at(s):
        e, phi, psi = env(s), plan.phase(s), heading(s)
        lat = sway * e * np.cos(2 * np.pi * (phi - D / 2))  # over the stance foot
        return path(s) + lat[:, None] * np.stack([np.cos(psi), -np.sin(psi)], axis=-1)

    feet = plan.feet(t)
    e, phi = env(t), plan.phase(t)
    root_rot, root_xz = root_rot_at(t), root_xz_at(t)
    if run:
        y = _run_height(rig, t, plan, root_xz_at, root_rot_at, env, Y0 - run_drop, run_reach)
    else:
        def nominal_at(s):
            return Y0 - drop * env(s) + bob * env(s) * np.cos(4 * np.pi * (plan.phase(s) - D / 2))

        y = _walk_height(rig, t, plan, root_xz_at, root_rot_at, env, nominal_at)
    root_pos = np.stack([root_xz[:, 0], y, root_xz[:, 1]], axis=-1)

    c1 = np.cos(2 * np.pi * phi)
    yaw_rel = -pelvis_yaw * e * c1
    roll = -pelvis_roll * e * np.cos(2 * np.pi * (phi - D / 2))
    local = _spine(t, flex=0.6 * lean * e, side=-0.9 * roll, twist=-2.0 * yaw_rel)
    local.update(_head(t, flex=-0.8 * lean * e, twist=yaw_rel))
    swing = arm_swing * e * c1
    down = _arms_down(t)
    for left, sw, el in ((True, -swing, (1 - c1) / 2), (False, swing, (1 + c1) / 2)):
        local.update(_arm(t, elev=(-RELAXED_ARM + arm_lift * e) * down, swing=sw + 0.3 * lean * e,
                          elbow=_RELAXED_ELBOW * down + elbow * e + elbow_swing * e * el, left=left))
    # A runner's swinging leg reaches for the floor with the knee as bent as at touch-down.
    hang = 1.0 - (1.0 - run_reach) * e if run else 1.0
    return _Spec(t=t, root_pos=root_pos, root_rot=root_rot, local=local, feet=feet, hang_reach=hang)


def _run_height(rig, t, plan: _GaitPlan, root_xz_at, root_rot_at, env, y_low, reach):
    """Pelvis height of a run [m], shape (T,): exact parabolas in flight, cubic Hermite pieces in
    stance. Contact heights are the lower of the nominal y_low (faded in by env) and the height at
    which the touching-down / lifting-off leg still reaches its foot with reach * rest length."""
    Y0 = rig.pelvis_height
    events = plan.contact_events()
    times = np.array([x for td, lo, _ in events for x in (td, lo)])
    sides = np.array([side for _, _, side in events for _ in (0, 1)])
    feet = plan.feet(times)
    e = env(times)
    heights = Y0 + (y_low - Y0) * e
    for side in (0, 1):
        m = sides == side
        foot = _Foot(*(getattr(feet[side], f)[m] for f in ("ground", "yaw", "pitch", "lift")))
        A = rig.ankle_target(side, foot)
        r = 1.0 - (1.0 - reach) * e[m]
        reachable = rig.reach_height(side, root_xz_at(times[m]), root_rot_at(times[m]), A, reach=r)
        heights[m] = np.minimum(heights[m], reachable)
    keys = []
    n = len(events)
    slopes = np.zeros(2 * n)
    for i in range(n - 1):
        lo, td_next = times[2 * i + 1], times[2 * i + 2]
        duration = td_next - lo
        if duration > 1e-4:
            slopes[2 * i + 1], slopes[2 * i + 2] = _flight(heights[2 * i + 1], heights[2 * i + 2], duration)
    for i in range(2 * n):
        # Drop a touch-down that coincides with the previous lift-off (no flight yet).
        if keys and times[i] - keys[-1][0] <= 1e-4:
            keys[-1] = (keys[-1][0], 0.5 * (keys[-1][1] + heights[i]), 0.0)
            continue
        keys.append((times[i], heights[i], slopes[i]))
    return _hermite(t, keys)


def _walk(rig, t):
    g = _Gait(cadence=0.92, duty=0.62, lift=0.11, half_width=0.06, toe_out=6 * _DEG, lift_peak=0.35,
              strike=14 * _DEG, push=28 * _DEG)
    return _gait_clip(rig, t, g, speed=1.25)


def _walk_fast(rig, t):
    g = _Gait(cadence=1.02, duty=0.6, lift=0.12, half_width=0.055, toe_out=5 * _DEG, lift_peak=0.35,
              strike=16 * _DEG, push=32 * _DEG)
    return _gait_clip(rig, t, g, speed=1.7, ramp=(0.4, 2.4), arm_swing=26 * _DEG, elbow=14 * _DEG,
                      elbow_swing=20 * _DEG, lean=5 * _DEG, pelvis_yaw=6 * _DEG, bob=0.014, drop=0.025)


def _walk_curve(rig, t):
    g = _Gait(cadence=0.9, duty=0.62, lift=0.1, half_width=0.06, toe_out=6 * _DEG, lift_peak=0.35,
              strike=12 * _DEG, push=26 * _DEG)
    env = lambda s: _ease(s, 0.45, 2.2)  # noqa: E731
    # A left turn on a circle of radius 2.2 m at 1.1 m/s: heading rate = speed / radius.
    heading = _integral(lambda s: (1.1 / 2.2) * env(s), float(t[-1]))
    return _gait_clip(rig, t, g, speed=1.1, heading=heading, pelvis_roll=3.5 * _DEG)


def _run(rig, t):
    g = _Gait(cadence=1.4, duty=0.36, duty0=0.5, lift=0.22, half_width=0.045, toe_out=4 * _DEG,
              lift_peak=0.33, strike=6 * _DEG, push=30 * _DEG, flat=(0.15, 0.45))
    return _gait_clip(rig, t, g, speed=2.7, ramp=(0.4, 2.4), run=True, lean=9 * _DEG, arm_swing=38 * _DEG,
                      elbow=70 * _DEG, elbow_swing=18 * _DEG, arm_lift=8 * _DEG, pelvis_yaw=7 * _DEG,
                      pelvis_roll=3 * _DEG, sway=0.012)


def _side_step(rig, t):
    g = _Gait(cadence=0.85, duty=0.66, lift=0.06, half_width=0.16, lift_peak=0.5, strike=4 * _DEG,
              push=10 * _DEG, swing_ankle=None, travel_delay=0.12)
    # To the left for ~2.4 s, then back to the right, then stop; the stepping fades out at the end.
    speed_fn = lambda s: 0.32 * (_ease(s, 0.5, 1.3) - 2.0 * _ease(s, 3.0, 4.0) + _ease(s, 5.8, 6.6))  # noqa: E731
    activity = lambda s: _ease(s, 0.45, 1.2) - _ease(s, 6.6, 7.3)  # noqa: E731
    # Sideways travel: direction +pi/2 from the heading (the body's left); negative speed goes right.
    return _gait_clip(rig, t, g, speed=0.0, env=activity, speed_fn=speed_fn, direction=np.pi / 2,
                      arm_swing=4 * _DEG, pelvis_yaw=1 * _DEG, pelvis_roll=3 * _DEG, sway=0.03, bob=0.006)


def _turn_in_place(rig, t):
    g = _Gait(cadence=1.0, duty=0.65, lift=0.07, half_width=0.1, toe_out=4 * _DEG, lift_peak=0.5,
              strike=4 * _DEG, push=12 * _DEG, swing_ankle=None, travel_delay=0.12)
    # Half a turn to the left, a pause, and half a turn back to the right.
    heading = lambda s: np.pi * (_ease(s, 0.9, 3.4) - _ease(s, 4.2, 6.7))  # noqa: E731
    activity = lambda s: _ease(s, 0.45, 1.1) - _ease(s, 6.7, 7.3)  # noqa: E731
    return _gait_clip(rig, t, g, speed=0.0, env=activity, heading=heading, arm_swing=6 * _DEG,
                      pelvis_yaw=2 * _DEG, pelvis_roll=2 * _DEG, sway=0.015, bob=0.006, drop=0.01)


def _stance_spec(rig: _Rig, t, feet, *, dx=0.0, dy=0.0, dz=0.0, yaw=0.0, tilt=0.0, roll=0.0, local=None,
                 env=None, reach=0.997) -> _Spec:
    """A spec for clips whose pelvis moves over (mostly) planted feet.

    dx, dy, dz [m]: pelvis offsets from its rest position, shape (T,) or scalars (dy is the nominal
    drop, lowered further wherever a foot would otherwise be out of reach); yaw, tilt, roll [rad]:
    pelvis orientation (see _root_rot); env in [0, 1] fades the reach constraint in (default: over
    the first 0.6 s), so frame 0 is the exact rest pose.
    """
    f = lambda a: np.broadcast_to(np.asarray(a, dtype=np.float64), np.shape(t))  # noqa: E731
    root_rot = _root_rot(t, yaw=yaw, tilt=tilt, roll=roll)
    root_xz = np.stack([rig.J[0, 0] + f(dx), rig.J[0, 2] + f(dz)], axis=-1)
    env = _ease(t, 0.0, 0.6) if env is None else env
    y = _fit_height(rig, t, rig.pelvis_height + f(dy), root_xz, root_rot, feet, env, reach=reach)
    root_pos = np.stack([root_xz[:, 0], y, root_xz[:, 1]], axis=-1)
    return _Spec(t=t, root_pos=root_pos, root_rot=root_rot, local=local or {}, feet=tuple(feet),
                 height_from_grid=True)


def _ballistic_spec(rig: _Rig, t, *, y_keys, feet_at, dx_at, dz_at, tilt_at, yaw_at=None, roll_at=None,
                    local=None, reach=0.99) -> _Spec:
    """A spec with jumps: pelvis height from Hermite keys in which a key may be ("takeoff", time,
    flight duration) -- replaced by an exact ballistic flight from the highest pelvis height at
    which both legs still reach their feet (with reach * rest hip-ankle distance) at take-off to
    the same at landing.

    y_keys: [(time, y, vy) | ("takeoff", time, duration)]; feet_at(s) -> (left, right) _Foot;
    dx_at, dz_at, tilt_at, yaw_at, roll_at: functions of time (pelvis offsets [m], angles [rad]).
    """
    zero = lambda s: np.zeros(np.shape(s))  # noqa: E731
    yaw_at, roll_at = yaw_at or zero, roll_at or zero

    def root_rot_at(s):
        return _root_rot(s, yaw=yaw_at(s), tilt=tilt_at(s), roll=roll_at(s))

    def root_xz_at(s):
        return np.stack([rig.J[0, 0] + dx_at(s), rig.J[0, 2] + dz_at(s)], axis=-1)

    def contact_height(time):
        s = np.array([time])
        feet = feet_at(s)
        return min(float(rig.reach_height(side, root_xz_at(s), root_rot_at(s), rig.ankle_target(side, feet[side]),
                                          reach=reach)[0]) for side in (0, 1))

    keys = []
    airborne = np.zeros(np.shape(t))
    for key in y_keys:
        if key[0] == "takeoff":
            _, t0, duration = key
            y0, y1 = contact_height(t0), contact_height(t0 + duration)
            v0, v1 = _flight(y0, y1, duration)
            keys += [(t0, y0, v0), (t0 + duration, y1, v1)]
            airborne += _ease(t, t0 - 0.2, t0 - 0.05) - _ease(t, t0 + duration + 0.05, t0 + duration + 0.2)
        else:
            keys.append(key)
    y = _hermite(t, keys)
    root_xz = root_xz_at(t)
    root_pos = np.stack([root_xz[:, 0], y, root_xz[:, 1]], axis=-1)
    # In the air the legs hang with the knees as bent as at take-off and landing.
    hang = 1.0 - (1.0 - reach) * np.clip(airborne, 0.0, 1.0)
    return _Spec(t=t, root_pos=root_pos, root_rot=root_rot_at(t), local=local or {}, feet=tuple(feet_at(t)),
                 hang_reach=hang)


def _jump(rig, t):
    """Two countermovement jumps: one straight up (0.28 m), one forward (0.5 m, 0.2 m high)."""
    Y0 = rig.pelvis_height
    fl1 = 2.0 * np.sqrt(2.0 * GRAVITY * 0.28) / GRAVITY
    fl2 = 2.0 * np.sqrt(2.0 * GRAVITY * 0.20) / GRAVITY
    to1, to2 = 1.75, 3.75
    ld1, ld2 = to1 + fl1, to2 + fl2
    hop = 0.5  # forward jump distance of the feet [m]
    # Forward speed of the pelvis in the second flight: from 0.1 m ahead of the feet to 0.1 m behind.
    vz = (hop - 0.2) / fl2

    def dz_at(s):
        return _hermite(s, [(0.0, 0.0, 0.0), (to1 - 0.5, 0.0, 0.0), (to1 - 0.25, -0.05, 0.0), (to1, 0.02, 0.0),
                            (ld1, 0.02, 0.0), (ld1 + 0.3, -0.04, 0.0), (to2 - 0.5, 0.0, 0.0),
                            (to2 - 0.25, -0.06, 0.0), (to2, 0.1, vz), (ld2, 0.1 + vz * fl2, vz),
                            (ld2 + 0.35, hop - 0.03, 0.0), (ld2 + 0.9, hop, 0.0)])

    def tilt_at(s):
        return _track(s, [(0.0, 0.0), (to1 - 0.55, 0.0), (to1 - 0.22, 30 * _DEG), (to1, 6 * _DEG), (ld1, 4 * _DEG),
                          (ld1 + 0.3, 24 * _DEG), (ld1 + 0.8, 2 * _DEG), (to2 - 0.55, 0.0), (to2 - 0.22, 32 * _DEG),
                          (to2, 14 * _DEG), (ld2, 8 * _DEG), (ld2 + 0.32, 28 * _DEG), (ld2 + 0.9, 0.0)])

    def feet_at(s):
        zf = hop * _ease(s, to2, ld2)
        pitch = _track(s, [(0.0, 0.0), (to1 - 0.25, 0.0), (to1, -32 * _DEG), (ld1, -22 * _DEG), (ld1 + 0.12, 0.0),
                           (to2 - 0.25, 0.0), (to2, -32 * _DEG), (ld2, -20 * _DEG), (ld2 + 0.12, 0.0)])
        # A small tuck of the feet in the air; the rest of the lift comes from the legs' reach.
        tuck = 0.05 * _bump((s - to1) / fl1) + 0.08 * _bump((s - to2) / fl2)
        return tuple(_moved_foot(rig, side, s, pitch=pitch, ground=np.stack(
            [np.zeros_like(s), tuck, zf], axis=-1)) for side in (0, 1))

    # Each countermovement sinks the pelvis over 0.4-0.45 s: a rest-to-rest cubic's largest downward
    # acceleration is 6 depth / duration^2, which then stays under gravity's.
    y_keys = [(0.0, Y0, 0.0), (to1 - 0.7, Y0, 0.0), (to1 - 0.25, Y0 - 0.2, 0.0), ("takeoff", to1, fl1),
              (ld1 + 0.3, Y0 - 0.17, 0.0), (ld1 + 0.8, Y0 - 0.005, 0.0),
              (to2 - 0.25, Y0 - 0.22, 0.0), ("takeoff", to2, fl2), (ld2 + 0.32, Y0 - 0.2, 0.0),
              (ld2 + 0.9, Y0, 0.0)]
    swing = _track(t, [(0.0, 0.0), (to1 - 0.55, 0.0), (to1 - 0.22, -50 * _DEG), (to1 + 0.1, 150 * _DEG),
                       (ld1, 90 * _DEG), (ld1 + 0.45, 0.0), (to2 - 0.55, 0.0), (to2 - 0.22, -55 * _DEG),
                       (to2 + 0.1, 120 * _DEG), (ld2, 70 * _DEG), (ld2 + 0.5, 0.0)])
    tilt = tilt_at(t)
    local = _relaxed_arms(t, swing_l=swing, swing_r=swing)
    local.update(_spine(t, flex=0.5 * tilt))
    local.update(_head(t, flex=-0.9 * tilt))
    return _ballistic_spec(rig, t, y_keys=y_keys, feet_at=feet_at, dx_at=lambda s: np.zeros(np.shape(s)),
                           dz_at=dz_at, tilt_at=tilt_at, local=local)


def _jumping_jacks(rig, t):
    """Four jumping jacks: hop the feet apart with the arms overhead and back together, on the balls
    of the feet, with short ballistic flights (0.22 s)."""
    Y0 = rig.pelvis_height
    flight, period = 0.22, 0.5
    takeoffs = 1.5 + period * np.arange(8)
    landings = takeoffs + flight
    width = 0.2  # each foot moves out by this much [m]

    def out_state(s):
        return sum(((-1) ** k) * _ease(s, to, ld) for k, (to, ld) in enumerate(zip(takeoffs, landings)))

    def feet_at(s):
        o = out_state(s)
        keys = [(0.0, 0.0), (1.2, 0.0), (takeoffs[0], -26 * _DEG)]
        for k, ld in enumerate(landings):
            keys += [(ld, -18 * _DEG), (ld + 0.14, -7 * _DEG)]
            if k + 1 < len(takeoffs):
                keys.append((takeoffs[k + 1], -26 * _DEG))
        keys[-1] = (landings[-1] + 0.3, 0.0)
        pitch = _track(s, keys)
        return tuple(_moved_foot(rig, side, s, pitch=pitch, yaw=sign * 12 * _DEG * o,
                                 ground=np.stack([sign * width * o, np.zeros_like(s), np.zeros_like(s)], -1))
                     for side, sign in ((0, 1.0), (1, -1.0)))

    y_keys = [(0.0, Y0, 0.0), (1.0, Y0, 0.0), (1.3, Y0 - 0.07, 0.0)]
    for k, to in enumerate(takeoffs):
        y_keys.append(("takeoff", to, flight))
    y_keys += [(landings[-1] + 0.3, Y0 - 0.07, 0.0), (landings[-1] + 0.8, Y0, 0.0)]
    elev_keys = [(0.0, 0.0), (0.9, -RELAXED_ARM), (takeoffs[0] - 0.05, -RELAXED_ARM)]
    for k, ld in enumerate(landings):
        elev_keys.append((ld + 0.02, 76 * _DEG if k % 2 == 0 else -68 * _DEG))
    elev_keys.append((landings[-1] + 0.5, -RELAXED_ARM))
    elev = _track(t, elev_keys)
    up = np.clip(elev / (76 * _DEG), 0.0, 1.0)
    local = _arm(t, elev=elev, plane=6 * _DEG * up, elbow=_RELAXED_ELBOW * _arms_down(t) * (1 - up), left=True)
    local.update(_arm(t, elev=elev, plane=6 * _DEG * up, elbow=_RELAXED_ELBOW * _arms_down(t) * (1 - up),
                      left=False))
    local.update(_head(t, flex=-4 * _DEG * up))
    zero = lambda s: np.zeros(np.shape(s))  # noqa: E731
    return _ballistic_spec(rig, t, y_keys=y_keys, feet_at=feet_at, dx_at=zero, dz_at=zero,
                           tilt_at=lambda s: 3 * _DEG * _ease(s, 1.0, 1.4) * (1 - _ease(s, 5.6, 6.2)), local=local)


def _squat(rig, t):
    """Three bodyweight squats (pelvis 0.38 m down), arms raised forward as a counterweight."""
    keys = [(0.0, 0.0), (1.0, 0.0)]
    for start in (1.0, 3.1, 5.2):
        keys += [(start + 0.9, 1.0), (start + 1.2, 1.0), (start + 2.0, 0.0), (start + 2.1, 0.0)]
    d = _track(t, keys)
    arms = _track(t, [(k[0] - 0.1, k[1]) for k in keys])
    local = _relaxed_arms(t, swing_l=80 * _DEG * arms, swing_r=80 * _DEG * arms)
    local.update(_spine(t, flex=14 * _DEG * d))
    local.update(_head(t, flex=-30 * _DEG * d))
    feet = [_still_foot(rig, side, t) for side in (0, 1)]
    return _stance_spec(rig, t, feet, dy=-0.38 * d, dz=-0.13 * d, tilt=30 * _DEG * d, local=local)


def _arm_raises(rig, t):
    """Arms raised forward to overhead, then sideways to overhead, then forward to shoulder height."""
    swing = _track(t, [(0.0, 0.0), (1.0, 0.0), (2.3, 160 * _DEG), (2.6, 160 * _DEG), (3.8, 0.0), (5.9, 0.0),
                       (6.8, 90 * _DEG), (7.1, 90 * _DEG), (7.9, 0.0)])
    lateral = _track(t, [(0.0, 0.0), (3.9, 0.0), (4.8, 1.0), (5.0, 1.0), (5.9, 0.0)])
    elev = -RELAXED_ARM * _arms_down(t) + (RELAXED_ARM + 78 * _DEG) * lateral
    up = np.clip(swing / (160 * _DEG), 0.0, 1.0) + lateral
    local = {}
    for left in (True, False):
        local.update(_arm(t, elev=elev, swing=swing, elbow=_RELAXED_ELBOW * _arms_down(t) * (1 - np.clip(up, 0, 1)),
                          left=left))
    local.update(_spine(t, flex=-6 * _DEG * np.clip(up, 0, 1)))
    local.update(_head(t, flex=-10 * _DEG * np.clip(up, 0, 1)))
    feet = [_still_foot(rig, side, t) for side in (0, 1)]
    return _stance_spec(rig, t, feet, dy=-0.01 * _ease(t, 0.3, 1.0), local=local)


def _arm_swings(rig, t):
    """Warm-up arm swings: alternating pendulum swings that grow to 70 deg, then both arms raised to
    shoulder height swinging open and crossed in front of the chest."""
    amp = 70 * _DEG * _track(t, [(0.0, 0.0), (1.0, 0.0), (2.2, 1.0), (3.6, 1.0), (4.2, 0.0)])
    osc = np.sin(2 * np.pi * 0.9 * (t - 1.0))
    horiz = _track(t, [(0.0, 0.0), (3.9, 0.0), (4.5, 1.0), (6.6, 1.0), (7.2, 0.0)])
    cross = horiz * (45 * _DEG - 50 * _DEG * np.cos(2 * np.pi * 0.8 * (t - 4.5)))
    elev_base = -RELAXED_ARM * _arms_down(t) * (1 - horiz)
    local = _arm(t, elev=elev_base + 4 * _DEG * horiz, swing=amp * osc, plane=cross,
                 elbow=(_RELAXED_ELBOW + 6 * _DEG) * _arms_down(t) * (1 - 0.5 * horiz), left=True)
    local.update(_arm(t, elev=elev_base - 4 * _DEG * horiz, swing=-amp * osc, plane=cross,
                      elbow=(_RELAXED_ELBOW + 6 * _DEG) * _arms_down(t) * (1 - 0.5 * horiz), left=False))
    local.update(_spine(t, twist=-6 * _DEG * (amp / (70 * _DEG)) * osc))
    feet = [_still_foot(rig, side, t) for side in (0, 1)]
    return _stance_spec(rig, t, feet, dy=-0.01 * _ease(t, 0.3, 1.0), local=local)


def _torso_twist(rig, t):
    """Standing torso twists: chest turns 50 deg to each side, hands held in front of the chest."""
    env = _track(t, [(0.0, 0.0), (1.0, 0.0), (1.8, 1.0), (6.0, 1.0), (6.8, 0.0)])
    twist = 50 * _DEG * env * np.sin(2 * np.pi * 0.45 * (t - 1.0))
    pose = _track(t, [(0.0, 0.0), (0.3, 0.0), (1.2, 1.0), (6.5, 1.0), (7.3, 0.0)])
    # Hands in front of the chest: upper arms forward and out, turned inwards (twist), elbows bent.
    elev = -RELAXED_ARM * _arms_down(t) * (1 - pose) - 45 * _DEG * pose
    local = {}
    for left in (True, False):
        local.update(_arm(t, elev=elev, swing=55 * _DEG * pose, twist=70 * _DEG * pose,
                          elbow=_RELAXED_ELBOW * _arms_down(t) + 100 * _DEG * pose, left=left))
    local.update(_spine(t, twist=0.78 * twist, side=0.0))
    local.update(_head(t, twist=0.1 * twist))
    feet = [_still_foot(rig, side, t) for side in (0, 1)]
    return _stance_spec(rig, t, feet, dy=-0.025 * pose, yaw=0.22 * twist, local=local)


def _kick(rig, t):
    """Front kicks: weight onto the left leg, right front kick at hip height, back down; then the same
    with the left leg. Arms in a guard."""
    def kick_tracks(t0):
        z = _track(t, [(t0, 0.0), (t0 + 0.3, 0.1), (t0 + 0.52, 0.74), (t0 + 0.72, 0.16), (t0 + 1.0, 0.0)])
        lift = _track(t, [(t0, 0.0), (t0 + 0.3, 0.3), (t0 + 0.52, 0.55), (t0 + 0.72, 0.3), (t0 + 1.0, 0.0)])
        pitch = _track(t, [(t0, 0.0), (t0 + 0.25, -25 * _DEG), (t0 + 0.52, -15 * _DEG), (t0 + 0.8, -25 * _DEG),
                           (t0 + 1.0, 0.0)])
        return z, lift, pitch

    t_r, t_l = 1.4, 3.6
    shift = _track(t, [(0.0, 0.0), (0.7, 0.0), (1.3, 1.0), (2.5, 1.0), (3.0, 0.0), (3.5, -1.0), (4.7, -1.0),
                       (5.3, 0.0)])
    ext_r = _track(t, [(0.0, 0.0), (t_r + 0.2, 0.0), (t_r + 0.52, 1.0), (t_r + 0.9, 0.0)])
    ext_l = _track(t, [(0.0, 0.0), (t_l + 0.2, 0.0), (t_l + 0.52, 1.0), (t_l + 0.9, 0.0)])
    feet = []
    for side, t0 in ((0, t_l), (1, t_r)):
        z, lift, pitch = kick_tracks(t0)
        foot = _moved_foot(rig, side, t, pitch=pitch)
        foot.ground[:, 2] += z
        foot.lift += lift
        # In the air the kicking foot follows its shin, pointed by 20 deg.
        foot.relax, foot.relax_angle = _smoothstep(lift / 0.3), 20 * _DEG
        feet.append(foot)
    guard = _track(t, [(0.0, 0.0), (0.3, 0.0), (1.1, 1.0), (4.9, 1.0), (5.6, 0.0)])
    local = {}
    for left, ext_same, ext_other in ((True, ext_l, ext_r), (False, ext_r, ext_l)):
        local.update(_arm(t, elev=-RELAXED_ARM * _arms_down(t) * (1 - guard) - 62 * _DEG * guard,
                          swing=guard * (40 * _DEG - 30 * _DEG * ext_same + 10 * _DEG * ext_other),
                          twist=25 * _DEG * guard, elbow=_RELAXED_ELBOW * _arms_down(t) + 110 * _DEG * guard,
                          left=left))
    kick = ext_r + ext_l
    local.update(_spine(t, flex=-8 * _DEG * kick, side=-6 * _DEG * shift))
    local.update(_head(t, flex=6 * _DEG * kick))
    return _stance_spec(rig, t, feet, dx=0.075 * shift, dy=-0.03 * shift**2, tilt=-10 * _DEG * kick,
                        roll=3 * _DEG * shift, local=local)


def _dance(rig, t):
    """A step-touch groove at 120 beats/min: bars of step out, touch in, step back, touch back,
    alternating right and left, with a bounce on every beat, hip sway, pumping arms and a bar
    of hands up; it ends in a pose with the arms in a V."""
    bars = ((1.0, 1.0), (3.0, -1.0), (5.0, 1.0))  # (start [s], +1: to the right, -1: to the left)
    steps = {0: [], 1: []}
    pitch_keys = {0: [(0.0, 0.0)], 1: [(0.0, 0.0)]}
    x_keys = [(0.0, 0.0), (1.0, 0.0)]
    for t0, d in bars:
        lead, trail = (1, 0) if d > 0 else (0, 1)
        out = -0.24 * d  # the lead foot steps out to the body's right (-x) for d = +1
        steps[lead] += [(t0 + 0.05, t0 + 0.4, out, 0.0, 0.07), (t0 + 1.55, t0 + 1.9, -out, 0.0, 0.06)]
        steps[trail] += [(t0 + 0.55, t0 + 0.9, out, 0.0, 0.06), (t0 + 1.05, t0 + 1.4, -out, 0.0, 0.07)]
        pitch_keys[trail] += [(t0 + 0.55, 0.0), (t0 + 0.9, -14 * _DEG), (t0 + 1.0, -14 * _DEG), (t0 + 1.4, 0.0)]
        pitch_keys[lead] += [(t0 + 1.55, 0.0), (t0 + 1.9, -12 * _DEG), (t0 + 2.0, -12 * _DEG), (t0 + 2.3, 0.0)]
        x_keys += [(t0 + 0.45, 0.8 * out), (t0 + 0.95, out), (t0 + 1.45, 0.1 * out), (t0 + 1.95, 0.0)]
    feet = []
    for side in (0, 1):
        keys = sorted(pitch_keys[side])
        feet.append(_moved_foot(rig, side, t, steps=steps[side], pitch=_track(t, keys)))
    groove = _track(t, [(0.0, 0.0), (0.6, 0.0), (1.0, 1.0), (7.0, 1.0), (7.5, 0.0)])
    beat = 2.0 * (t - 1.0)  # beats since the music started
    bounce = 0.5 * (1 - np.cos(2 * np.pi * beat))
    dx = _track(t, x_keys)
    dx_pose = _track(t, [(0.0, 0.0), (7.1, 0.0), (7.6, -0.04), (8.5, -0.04)])
    hip = dx / 0.24
    # Arms: pumping (elbows bent, alternating forward swings), a bar of hands up, a V at the end.
    up = _track(t, [(0.0, 0.0), (3.0, 0.0), (3.4, 1.0), (4.6, 1.0), (5.0, 0.0), (7.0, 0.0), (7.5, 1.0), (8.5, 1.0)])
    pump = groove * (1 - up)
    osc = np.sin(np.pi * beat)
    elev = (-RELAXED_ARM * _arms_down(t) + 16 * _DEG * pump) * (1 - up) + 48 * _DEG * up
    local = _arm(t, elev=elev, swing=pump * (30 * _DEG + 30 * _DEG * osc) + up * 10 * _DEG * osc, plane=8 * _DEG * up,
                 elbow=_RELAXED_ELBOW * _arms_down(t) * (1 - up) + 90 * _DEG * pump + 15 * _DEG * up, left=True)
    local.update(_arm(t, elev=elev, swing=pump * (30 * _DEG - 30 * _DEG * osc) - up * 10 * _DEG * osc,
                      plane=8 * _DEG * up, elbow=_RELAXED_ELBOW * _arms_down(t) * (1 - up) + 90 * _DEG * pump
                      + 15 * _DEG * up, left=False))
    roll = 7 * _DEG * hip + 5 * _DEG * dx_pose / 0.04
    local.update(_spine(t, side=-1.2 * roll, twist=12 * _DEG * groove * osc, flex=3 * _DEG * groove))
    local.update(_head(t, flex=6 * _DEG * groove * np.sin(2 * np.pi * beat), side=0.4 * roll))
    return _stance_spec(rig, t, feet, dx=dx + dx_pose, dy=-0.02 * groove - 0.035 * groove * bounce, roll=roll,
                        yaw=-8 * _DEG * groove * osc, local=local)


def _bend_and_reach(rig, t):
    """Bend forward to reach the toes, rise to reach overhead on the toes, then side bends with one
    arm overhead to each side."""
    bend = _track(t, [(0.0, 0.0), (1.0, 0.0), (2.6, 1.0), (3.0, 1.0), (4.3, 0.0)])
    overhead = _track(t, [(0.0, 0.0), (3.2, 0.0), (4.3, 1.0), (4.9, 1.0), (5.6, 0.0)])
    rise = _track(t, [(0.0, 0.0), (4.0, 0.0), (4.5, 1.0), (4.9, 1.0), (5.4, 0.0)])
    side = _track(t, [(0.0, 0.0), (5.4, 0.0), (6.3, 1.0), (6.7, 1.0), (7.4, 0.0), (8.3, -1.0), (8.7, -1.0),
                      (9.5, 0.0)])
    left_up = np.clip(-side, 0.0, 1.0)  # bending to the right lifts the left arm
    right_up = np.clip(side, 0.0, 1.0)
    local = {}
    for left, arm_up in ((True, left_up), (False, right_up)):
        elev = -RELAXED_ARM * _arms_down(t) * (1 - arm_up) + 75 * _DEG * arm_up
        local.update(_arm(t, elev=elev, swing=bend * 80 * _DEG + overhead * 165 * _DEG,
                          elbow=_RELAXED_ELBOW * _arms_down(t) * (1 - overhead) * (1 - arm_up) + 10 * _DEG * arm_up,
                          left=left))
    local.update(_spine(t, flex=40 * _DEG * bend - 8 * _DEG * overhead, side=28 * _DEG * side))
    local.update(_head(t, flex=-12 * _DEG * bend - 10 * _DEG * overhead, side=6 * _DEG * side))
    pitch = -22 * _DEG * rise
    feet = [_moved_foot(rig, s_, t, pitch=pitch) for s_ in (0, 1)]
    return _stance_spec(rig, t, feet, dx=-0.05 * side, dy=-0.03 * bend + 0.05 * rise, dz=-0.12 * bend,
                        tilt=55 * _DEG * bend, roll=4 * _DEG * side, local=local)


def _lunge(rig, t):
    """Forward lunges: the right foot steps 0.75 m forward landing on its heel, the body sinks until
    the back knee is low (back heel up, toes bent), rises and steps back; then the left leg."""
    stride = 0.75
    starts = {1: 1.0, 0: 4.2}  # lunge start per side [s]; each lunge takes 3 s
    sink = np.zeros_like(t)
    fwd = np.zeros_like(t)
    feet = [None, None]
    for side, t0 in starts.items():
        other = 1 - side
        # The pelvis travels with the stepping foot, staying about midway between the feet, and
        # starts sinking while that foot is still in the air (an upright body could not reach it).
        sink += _track(t, [(t0, 0.0), (t0 + 0.1, 0.0), (t0 + 1.3, 1.0), (t0 + 1.6, 1.0), (t0 + 2.7, 0.0)])
        fwd += _ease(t, t0, t0 + 0.7) - _ease(t, t0 + 2.3, t0 + 2.9)
        # The stepping foot: out and back, landing heel first both times.
        pitch = _track(t, [(t0, 0.0), (t0 + 0.15, -12 * _DEG), (t0 + 0.7, 12 * _DEG), (t0 + 0.9, 0.0),
                           (t0 + 2.3, 0.0), (t0 + 2.45, -12 * _DEG), (t0 + 2.9, 8 * _DEG), (t0 + 3.05, 0.0)])
        foot = _moved_foot(rig, side, t, steps=[(t0, t0 + 0.7, 0.0, stride, 0.08),
                                                (t0 + 2.3, t0 + 2.9, 0.0, -stride, 0.08)], pitch=pitch)
        foot.relax = _bump((t - t0) / 0.7) + _bump((t - t0 - 2.3) / 0.6)
        foot.relax_angle = 5 * _DEG
        if feet[side] is not None:
            foot.pitch += feet[side].pitch
        feet[side] = foot
        # The back foot rolls onto its ball as the body sinks.
        back = -65 * _DEG * _track(t, [(t0, 0.0), (t0 + 0.1, 0.0), (t0 + 1.1, 1.0), (t0 + 1.6, 1.0), (t0 + 2.5, 0.0)])
        if feet[other] is None:
            feet[other] = _moved_foot(rig, other, t, pitch=back)
        else:
            feet[other].pitch = feet[other].pitch + back
    local = _relaxed_arms(t, swing_l=8 * _DEG * sink, swing_r=8 * _DEG * sink, elbow_l=20 * _DEG * sink,
                          elbow_r=20 * _DEG * sink)
    local.update(_spine(t, flex=-3 * _DEG * sink))
    return _stance_spec(rig, t, feet, dy=-0.3 * sink, dz=0.47 * stride * fwd, tilt=6 * _DEG * sink, local=local)


def _idle_sway(rig, t):
    """Standing at ease: slow weight shifts from foot to foot, breathing, looking around."""
    env = _ease(t, 0.4, 1.4)
    shift = env * np.sin(2 * np.pi * 0.22 * (t - 0.4))
    breathe = env * np.sin(2 * np.pi * 0.25 * t)
    local = _relaxed_arms(t, swing_l=3 * _DEG * shift, swing_r=-3 * _DEG * shift, extra_elev_l=2 * _DEG * shift,
                          extra_elev_r=-2 * _DEG * shift)
    local.update(_spine(t, flex=1.5 * _DEG * breathe, side=-2.5 * _DEG * shift))
    local.update(_head(t, twist=25 * _DEG * env * np.sin(2 * np.pi * 0.13 * (t - 0.4)), flex=4 * _DEG * breathe))
    feet = [_still_foot(rig, side, t) for side in (0, 1)]
    return _stance_spec(rig, t, feet, dx=0.035 * shift, dy=-0.012 * env, roll=2.5 * _DEG * shift,
                        yaw=3 * _DEG * shift, local=local)


# ---------------------------------------------------------------------------------------------
# Registry and public API
# ---------------------------------------------------------------------------------------------
def _builder(spec_fn: Callable, duration: float, name: str) -> Callable:
    """Wrap a spec function into builder(body, fps=30.0, betas=None) -> MotionClip."""

    def build(body: BodyModel, fps: float = 30.0, betas=None) -> MotionClip:
        try:
            fps = float(fps)
        except (TypeError, ValueError):
            raise InputError(f"procedural clip {name!r}: fps must be a number, got {fps!r}") from None
        if not np.isfinite(fps) or fps <= 0.0:
            raise InputError(f"procedural clip {name!r}: fps must be positive, got {fps}")
        if betas is not None:
            betas = body.check_betas(betas)[0]
        t = np.arange(int(round(duration * fps)) + 1) / fps
        rig = _Rig(body, betas)
        spec = spec_fn(rig, t)
        if spec.height_from_grid:
            # a fixed grid that covers every fps's last frame (at most half a frame past duration)
            grid = np.arange(int(round((duration + 0.25) * HEIGHT_RATE)) + 1) / HEIGHT_RATE
            spec.root_pos[:, 1] = CubicSpline(grid, spec_fn(rig, grid).root_pos[:, 1])(t)
        poses, trans = _solve(rig, spec)
        meta = {"source": "procedural", "generator": f"simgen.motion.procedural:{name}"}
        if betas is not None:
            meta["betas"] = [float(b) for b in betas]
        return MotionClip(name=name, fps=fps, poses=poses, trans=trans, meta=meta)

    build.__name__ = f"build_{name}"
    build.__doc__ = (f"Build the procedural clip {name!r} ({duration:g} s) for a body: "
                     f"(body, fps=30.0, betas=None) -> MotionClip.")
    return build


_CLIP_TABLE: list[tuple[str, Callable, float, str]] = [
    ("walk", _walk, 6.0, "Walk forward at 1.25 m/s (110 steps/min) from standing, arms swinging opposite the legs."),
    ("walk_fast", _walk_fast, 6.0, "Brisk walk at 1.7 m/s with a slight forward lean and larger arm swing."),
    ("walk_curve", _walk_curve, 7.0, "Walk at 1.1 m/s along a left-turning circle of 2.2 m radius."),
    ("run", _run, 5.0, "Jog starting from standing, up to 2.7 m/s with ballistic flight phases, bent elbows."),
    ("side_step", _side_step, 7.5, "Side steps to the left, then back to the right, then stop."),
    ("turn_in_place", _turn_in_place, 7.5, "Step around on the spot: half a turn left, pause, half a turn back."),
    ("jump", _jump, 5.5, "Two countermovement jumps with arm swing: 0.28 m straight up, then 0.5 m forward."),
    ("jumping_jacks", _jumping_jacks, 6.6, "Four jumping jacks: feet hop apart with the arms overhead and back."),
    ("squat", _squat, 7.5, "Three bodyweight squats, arms raised forward as a counterweight."),
    ("arm_raises", _arm_raises, 8.2,
     "Arms raised forward to overhead, sideways to overhead, forward to shoulder height."),
    ("arm_swings", _arm_swings, 7.5, "Alternating pendulum arm swings, then horizontal open-and-cross swings."),
    ("torso_twist", _torso_twist, 7.5, "Standing torso twists to each side with the hands in front of the chest."),
    ("kick", _kick, 6.0, "Front kick with the right leg, then with the left, arms in a guard."),
    ("dance", _dance, 8.5, "Step-touch groove at 120 bpm with bounce, hip sway, arm pumps and hands up."),
    ("bend_and_reach", _bend_and_reach, 9.8, "Bend to the toes, reach overhead on tiptoe, side bends each way."),
    ("lunge", _lunge, 8.0, "Forward lunge with the right leg, then with the left."),
    ("idle_sway", _idle_sway, 6.0, "Standing at ease: weight shifts, breathing, looking around."),
]

#: name -> (builder(body, fps=30.0, betas=None) -> MotionClip, one-line description).
PROCEDURAL_CLIPS: dict[str, tuple[Callable, str]] = {
    name: (_builder(fn, duration, name), description) for name, fn, duration, description in _CLIP_TABLE
}


def list_procedural() -> list[str]:
    """Names of the procedural clips, in library order."""
    return list(PROCEDURAL_CLIPS)


def make_clip(name: str, body: BodyModel, *, fps: float = 30.0, betas=None) -> MotionClip:
    """Build the procedural clip ``name`` for ``body`` at ``fps`` frames per second.

    The body's rest skeleton at shape ``betas`` (shape (B',), default zeros) sets the leg lengths
    and the foot placement, so the clip fits that shape: its feet stand on y = 0 and never go
    through the floor. (A clip made for one shape and played on a much shorter or taller one
    keeps the joint angles but not the contacts: a deep squat made for betas = 0 sinks the feet
    of a body at beta[0] = -2 by ~7 cm.) Returns a MotionClip with poses [rad] (T, 24, 3) and
    trans [m] (T, 3) in SMPL's convention. Raises InputError for an unknown name, a non-positive
    fps or unusable betas.
    """
    if name not in PROCEDURAL_CLIPS:
        raise InputError(f"unknown procedural clip {name!r}; known: {', '.join(PROCEDURAL_CLIPS)}")
    clip = PROCEDURAL_CLIPS[name][0](body, fps, betas)
    clip.meta["description"] = PROCEDURAL_CLIPS[name][1]
    return clip
