"""Per-frame motion descriptors fed to the wrinkle regressor and the linear baselines.

Two modes:

- ``"pose"`` (thesis 4.2.3): the 72 axis-angle values of the 24 SMPL joints, root included, as they
  are. The root's heading (rotation about the vertical) is then part of the input although it has no
  effect on the cloth.
- ``"pose_velocity"`` (ours, the default): the 23 joint rotations (69 axis-angle values), the root
  rotation with its heading removed (6 values: the first two columns of the matrix, continuous
  where axis-angle is not), the root's linear velocity [m/s] in the heading frame (3) and the
  heading's angular velocity [rad/s] (1): 79 values. The cloth responds to how the body moves
  through space (jumps, turns), which a regressor fed with poses alone has to infer from history;
  removing the heading makes a motion and the same motion facing elsewhere the same input.

Velocities are backward differences (frame 0 gets zero: simulations start from rest), so the
features of frame t depend only on frames t-1 and t, as a frame-by-frame runtime needs.
"""

from __future__ import annotations

import math

import torch

from simgen.body.torch_lbs import axis_angle_to_matrix_torch
from simgen.errors import InputError

__all__ = ["FEATURE_MODES", "feature_size", "motion_features", "heading_angle"]

FEATURE_MODES = ("pose", "pose_velocity")


def feature_size(mode: str) -> int:
    """Number of motion features per frame of a mode."""
    if mode == "pose":
        return 72
    if mode == "pose_velocity":
        return 79
    raise InputError(f"motion feature mode {mode!r} is not one of {', '.join(FEATURE_MODES)}")


def heading_angle(root_rotation: torch.Tensor) -> torch.Tensor:
    """Heading [rad] of root rotations (..., 3, 3): the angle about +Y of the body's front (+Z)."""
    front = root_rotation[..., :, 2]
    return torch.atan2(front[..., 0], front[..., 2])


def _rot_y(angle: torch.Tensor) -> torch.Tensor:
    c, s = torch.cos(angle), torch.sin(angle)
    z, o = torch.zeros_like(c), torch.ones_like(c)
    return torch.stack([c, z, s, z, o, z, -s, z, c], dim=-1).reshape(angle.shape + (3, 3))


def motion_features(poses: torch.Tensor, trans: torch.Tensor, fps: float, mode: str = "pose_velocity", *,
                    previous: tuple[torch.Tensor, torch.Tensor] | None = None) -> torch.Tensor:
    """Motion descriptors of consecutive frames.

    poses: axis-angle [rad], shape (..., T, 24, 3); trans [m], shape (..., T, 3); fps [1/s].
    previous: (pose (..., 24, 3), trans (..., 3)) of the frame before the first one, for streaming
    one frame at a time; None = the sequence starts at rest (zero velocity at frame 0).
    Returns features, shape (..., T, feature_size(mode)), in the dtype of ``poses``.
    """
    if poses.shape[-2:] != (24, 3) or trans.shape[-1] != 3 or poses.shape[:-2] != trans.shape[:-1]:
        raise InputError(f"poses (..., T, 24, 3) and trans (..., T, 3) must match, got {tuple(poses.shape)} "
                         f"and {tuple(trans.shape)}")
    if mode == "pose":
        return poses.reshape(poses.shape[:-2] + (72,))
    feature_size(mode)
    if fps <= 0:
        raise InputError(f"fps must be positive, got {fps}")
    if previous is not None:
        prev_pose, prev_trans = previous
        poses_ext = torch.cat([prev_pose[..., None, :, :], poses], dim=-3)
        trans_ext = torch.cat([prev_trans[..., None, :], trans], dim=-2)
    else:  # repeat frame 0: zero velocity there
        poses_ext = torch.cat([poses[..., :1, :, :], poses], dim=-3)
        trans_ext = torch.cat([trans[..., :1, :], trans], dim=-2)
    root = axis_angle_to_matrix_torch(poses_ext[..., 0, :])  # (..., T+1, 3, 3)
    heading = heading_angle(root)
    to_local = _rot_y(heading).transpose(-1, -2)  # world -> heading frame
    root_local = to_local @ root
    six = root_local[..., 1:, :, :2].reshape(poses.shape[:-2] + (6,))
    velocity = (trans_ext[..., 1:, :] - trans_ext[..., :-1, :]) * fps
    velocity = (to_local[..., 1:, :, :] @ velocity[..., None])[..., 0]
    dyaw = heading[..., 1:] - heading[..., :-1]
    dyaw = torch.remainder(dyaw + math.pi, 2 * math.pi) - math.pi  # unwrap
    joints = poses[..., 1:, :].reshape(poses.shape[:-2] + (69,))
    return torch.cat([joints, six, velocity, (dyaw * fps)[..., None]], dim=-1)
