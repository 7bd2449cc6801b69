"""Tests of simgen.motion.clearance (arms turned out of the torso).

What is checked is geometry nobody here chose: after the operation no tested arm point lies inside
the torso-and-legs surface (winding number of the posed open body), the turn moves the elbow away
from the body's midline, clips whose arms are clear come back unchanged, no other joint moves, and
the correction changes smoothly from frame to frame.
"""

from __future__ import annotations

import numpy as np
import pytest

from simgen.body import load
from simgen.body.model import SMPL_JOINT_NAMES
from simgen.errors import InputError
from simgen.motion import MotionClip, arm_torso_penetration, separate_arms
from simgen.motion.ops import posed_joints

J = {n: i for i, n in enumerate(SMPL_JOINT_NAMES)}


@pytest.fixture(scope="module")
def body():
    return load("open")


def _arms_down_clip(angles_deg) -> MotionClip:
    """T-pose with both upper arms lowered by the given angles [deg] (90 = hanging straight down)."""
    a = np.radians(np.asarray(angles_deg, dtype=np.float64))
    poses = np.zeros((len(a), 24, 3))
    poses[:, J["left_shoulder"], 2] = -a   # left arm along +X turns down about -Z
    poses[:, J["right_shoulder"], 2] = a
    poses[:, J["left_elbow"], 2] = -0.2   # a slight bend, as in a relaxed stance
    poses[:, J["right_elbow"], 2] = 0.2
    return MotionClip("arms_down", 30.0, poses, np.zeros((len(a), 3)), {})


@pytest.fixture(scope="module")
def sunk(body):
    # From arms clear of the body to arms pressed 10 degrees past vertical, into the hips.
    clip = _arms_down_clip(np.linspace(60.0, 100.0, 9))
    return clip, separate_arms(clip, body, clearance=0.005, smooth_s=0.1)


def test_arms_pressed_into_the_body_come_out(body, sunk):
    clip, fixed = sunk
    before = arm_torso_penetration(clip, body)
    assert before["left"][-1] > 0.01 and before["right"][-1] > 0.01   # centimetres inside at the end
    after = arm_torso_penetration(fixed, body)
    assert after["left"].max() == 0.0 and after["right"].max() == 0.0


def test_the_turn_moves_the_elbows_outward_and_leaves_the_rest_alone(body, sunk):
    clip, fixed = sunk
    J0, J1 = posed_joints(clip, body), posed_joints(fixed, body)
    left, right = J["left_elbow"], J["right_elbow"]
    last = -1
    assert J1[last, left, 0] > J0[last, left, 0] + 0.01
    assert J1[last, right, 0] < J0[last, right, 0] - 0.01
    others = [j for j in range(24) if j not in (J["left_shoulder"], J["right_shoulder"])]
    np.testing.assert_array_equal(fixed.poses[:, others], clip.poses[:, others])
    np.testing.assert_array_equal(fixed.trans, clip.trans)
    record = fixed.meta["history"][-1]
    assert record["op"] == "separate_arms"
    assert 0.0 < record["arms"]["left"]["max_turn_deg"] <= 25.0


def test_the_correction_is_smooth_in_time(body, sunk):
    clip, fixed = sunk
    # Elbow positions of the corrected clip: steps between frames no larger than the input's steps
    # plus a fraction of the largest correction (no frame-to-frame jump of the whole turn).
    J0, J1 = posed_joints(clip, body), posed_joints(fixed, body)
    e = J["left_elbow"]
    step_in = np.linalg.norm(np.diff(J0[:, e], axis=0), axis=1).max()
    step_out = np.linalg.norm(np.diff(J1[:, e], axis=0), axis=1).max()
    shift = np.linalg.norm(J1[:, e] - J0[:, e], axis=1).max()
    assert step_out < step_in + 0.6 * shift


def test_clear_arms_are_left_unchanged(body):
    clip = _arms_down_clip([0.0, 30.0, 45.0])
    fixed = separate_arms(clip, body)
    np.testing.assert_array_equal(fixed.poses, clip.poses)
    assert fixed.meta["history"][-1]["arms"]["left"]["frames_turned"] == 0


@pytest.mark.parametrize("kwargs, field", [({"clearance": -0.01}, "clearance"), ({"step_deg": 0.0}, "step_deg"),
                                           ({"max_angle_deg": float("nan")}, "max_angle_deg"),
                                           ({"smooth_s": "a"}, "smooth_s")])
def test_bad_parameters_are_one_clear_error(body, kwargs, field):
    with pytest.raises(InputError, match=f"separate_arms: {field}"):
        separate_arms(_arms_down_clip([90.0]), body, **kwargs)
