"""Rotation conversions shared by the body model and the motion code (numpy, float64).

Conventions: axis-angle vectors are rotation axis times angle [rad]; quaternions are (w, x, y, z),
unit norm; rotation matrices act on column vectors (x' = R @ x). Every function accepts arbitrary
leading batch dimensions ("...").

The torch versions used by the differentiable body forward live in ``simgen.body.torch_lbs``.
"""

from __future__ import annotations

import numpy as np

__all__ = [
    "axis_angle_to_matrix",
    "matrix_to_axis_angle",
    "axis_angle_to_quat",
    "quat_to_axis_angle",
    "quat_to_matrix",
    "matrix_to_quat",
    "quat_multiply",
    "quat_slerp",
    "euler_to_matrix",
]

_EPS = 1e-12


def axis_angle_to_matrix(axis_angle: np.ndarray) -> np.ndarray:
    """Rodrigues' formula. axis_angle [rad], shape (..., 3) -> rotation matrices, shape (..., 3, 3)."""
    aa = np.asarray(axis_angle, dtype=np.float64)
    angle = np.linalg.norm(aa, axis=-1, keepdims=True)  # (..., 1)
    small = angle < 1e-8
    safe = np.where(small, 1.0, angle)
    axis = aa / safe
    x, y, z = axis[..., 0], axis[..., 1], axis[..., 2]
    zeros = np.zeros_like(x)
    K = np.stack([zeros, -z, y, z, zeros, -x, -y, x, zeros], axis=-1).reshape(aa.shape[:-1] + (3, 3))
    s = np.sin(angle)[..., None]
    c = np.cos(angle)[..., None]
    eye = np.broadcast_to(np.eye(3), K.shape)
    R = eye + s * K + (1.0 - c) * (K @ K)
    # First-order expansion near zero keeps the map smooth: R = I + [aa]_x.
    ax, ay, az = aa[..., 0], aa[..., 1], aa[..., 2]
    K_small = np.stack([zeros, -az, ay, az, zeros, -ax, -ay, ax, zeros], axis=-1).reshape(K.shape)
    return np.where(small[..., None], eye + K_small, R)


def axis_angle_to_quat(axis_angle: np.ndarray) -> np.ndarray:
    """axis_angle [rad], shape (..., 3) -> unit quaternions (w, x, y, z), shape (..., 4)."""
    aa = np.asarray(axis_angle, dtype=np.float64)
    angle = np.linalg.norm(aa, axis=-1, keepdims=True)
    half = 0.5 * angle
    # sin(half)/angle -> 1/2 as angle -> 0
    scale = np.where(angle < 1e-8, 0.5 - angle**2 / 48.0, np.sin(half) / np.where(angle < 1e-8, 1.0, angle))
    return np.concatenate([np.cos(half), aa * scale], axis=-1)


def quat_to_axis_angle(quat: np.ndarray) -> np.ndarray:
    """Unit quaternions (w, x, y, z), shape (..., 4) -> axis-angle [rad] in [0, pi], shape (..., 3)."""
    q = np.asarray(quat, dtype=np.float64)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    q = np.where(q[..., :1] < 0.0, -q, q)  # shortest rotation
    w = np.clip(q[..., :1], -1.0, 1.0)
    v = q[..., 1:]
    sin_half = np.linalg.norm(v, axis=-1, keepdims=True)
    angle = 2.0 * np.arctan2(sin_half, w)
    scale = np.where(sin_half < 1e-8, 2.0 / np.maximum(w, _EPS), angle / np.where(sin_half < 1e-8, 1.0, sin_half))
    return v * scale


def quat_to_matrix(quat: np.ndarray) -> np.ndarray:
    """Unit quaternions (w, x, y, z), shape (..., 4) -> rotation matrices, shape (..., 3, 3)."""
    q = np.asarray(quat, dtype=np.float64)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    R = np.stack(
        [
            1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
        ],
        axis=-1,
    )
    return R.reshape(q.shape[:-1] + (3, 3))


def matrix_to_quat(matrix: np.ndarray) -> np.ndarray:
    """Rotation matrices, shape (..., 3, 3) -> unit quaternions (w, x, y, z) with w >= 0, shape (..., 4).

    Uses the numerically stable branch on the largest of (w, x, y, z).
    """
    m = np.asarray(matrix, dtype=np.float64)
    batch = m.shape[:-2]
    m = m.reshape(-1, 3, 3)
    tr = m[:, 0, 0] + m[:, 1, 1] + m[:, 2, 2]
    cand = np.stack(
        [1.0 + tr, 1.0 + m[:, 0, 0] - m[:, 1, 1] - m[:, 2, 2], 1.0 - m[:, 0, 0] + m[:, 1, 1] - m[:, 2, 2],
         1.0 - m[:, 0, 0] - m[:, 1, 1] + m[:, 2, 2]],
        axis=-1,
    )
    best = np.argmax(cand, axis=-1)
    q = np.empty((m.shape[0], 4))
    for k in range(4):
        sel = best == k
        if not np.any(sel):
            continue
        r = m[sel]
        s = 2.0 * np.sqrt(np.maximum(cand[sel, k], _EPS))
        if k == 0:
            q[sel] = np.stack([0.25 * s, (r[:, 2, 1] - r[:, 1, 2]) / s, (r[:, 0, 2] - r[:, 2, 0]) / s,
                               (r[:, 1, 0] - r[:, 0, 1]) / s], axis=-1)
        elif k == 1:
            q[sel] = np.stack([(r[:, 2, 1] - r[:, 1, 2]) / s, 0.25 * s, (r[:, 0, 1] + r[:, 1, 0]) / s,
                               (r[:, 0, 2] + r[:, 2, 0]) / s], axis=-1)
        elif k == 2:
            q[sel] = np.stack([(r[:, 0, 2] - r[:, 2, 0]) / s, (r[:, 0, 1] + r[:, 1, 0]) / s, 0.25 * s,
                               (r[:, 1, 2] + r[:, 2, 1]) / s], axis=-1)
        else:
            q[sel] = np.stack([(r[:, 1, 0] - r[:, 0, 1]) / s, (r[:, 0, 2] + r[:, 2, 0]) / s,
                               (r[:, 1, 2] + r[:, 2, 1]) / s, 0.25 * s], axis=-1)
    q /= np.linalg.norm(q, axis=-1, keepdims=True)
    q = np.where(q[:, :1] < 0.0, -q, q)
    return q.reshape(batch + (4,))


def matrix_to_axis_angle(matrix: np.ndarray) -> np.ndarray:
    """Rotation matrices, shape (..., 3, 3) -> axis-angle [rad], shape (..., 3)."""
    return quat_to_axis_angle(matrix_to_quat(matrix))


def quat_multiply(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton product a * b of quaternions (w, x, y, z), shapes (..., 4) -> (..., 4)."""
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    aw, ax, ay, az = np.moveaxis(a, -1, 0)
    bw, bx, by, bz = np.moveaxis(b, -1, 0)
    return np.stack(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ],
        axis=-1,
    )


def quat_slerp(q0: np.ndarray, q1: np.ndarray, t: np.ndarray | float) -> np.ndarray:
    """Spherical linear interpolation along the shorter arc.

    q0, q1: unit quaternions, shape (..., 4); t in [0, 1], broadcastable to (...,).
    Returns unit quaternions, shape (..., 4).
    """
    q0 = np.asarray(q0, dtype=np.float64)
    q1 = np.asarray(q1, dtype=np.float64)
    t = np.asarray(t, dtype=np.float64)[..., None]
    dot = np.sum(q0 * q1, axis=-1, keepdims=True)
    q1 = np.where(dot < 0.0, -q1, q1)
    dot = np.abs(dot)
    theta = np.arccos(np.clip(dot, -1.0, 1.0))
    sin_theta = np.sin(theta)
    near = sin_theta < 1e-6
    safe = np.where(near, 1.0, sin_theta)
    w0 = np.where(near, 1.0 - t, np.sin((1.0 - t) * theta) / safe)
    w1 = np.where(near, t, np.sin(t * theta) / safe)
    q = w0 * q0 + w1 * q1
    return q / np.linalg.norm(q, axis=-1, keepdims=True)


def euler_to_matrix(angles: np.ndarray, order: str) -> np.ndarray:
    """Intrinsic Euler angles [rad] -> rotation matrices.

    angles: shape (..., len(order)); order: axis letters such as "ZYX" (BVH channel order), applied
    as R = R_order[0] @ R_order[1] @ ... (intrinsic rotations, the BVH convention).
    Returns shape (..., 3, 3).
    """
    angles = np.asarray(angles, dtype=np.float64)
    if angles.shape[-1] != len(order):
        raise ValueError(f"euler_to_matrix: {angles.shape[-1]} angles for order {order!r}")
    R = np.broadcast_to(np.eye(3), angles.shape[:-1] + (3, 3)).copy()
    basis = {"X": np.array([1.0, 0.0, 0.0]), "Y": np.array([0.0, 1.0, 0.0]), "Z": np.array([0.0, 0.0, 1.0])}
    for k, axis in enumerate(order.upper()):
        if axis not in basis:
            raise ValueError(f"euler_to_matrix: unknown axis {axis!r} in order {order!r}")
        R = R @ axis_angle_to_matrix(angles[..., k : k + 1] * basis[axis])
    return R
