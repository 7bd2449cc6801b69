"""Tests of simgen.motion.clearance (arms turned out of the torso).

What is checked is geometry nobody here chose: after the operation no tested arm point lies inside
the torso-and-legs surface (winding number of the posed open body), the turn moves the elbow away
from the body's midline, clips whose arms are clear come back unchanged, no other joint moves, and
the arm eases out in the frames before it would sink in.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

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


def test_the_arm_eases_out_before_it_would_sink_in(body, sunk):
    clip, fixed = sunk
    # The search alone turns only frames whose arm is inside; the spreading over smooth_s makes the
    # arm start moving out in the frames before, so the turn does not appear from one frame to the next.
    inside = arm_torso_penetration(clip, body, clearance=0.005)["left"] > 0.0
    first = int(np.argmax(inside))
    assert first >= 2 and not inside[:first].any()
    turn = np.degrees((Rotation.from_rotvec(fixed.poses[:, J["left_shoulder"]])
                       * Rotation.from_rotvec(clip.poses[:, J["left_shoulder"]]).inv()).magnitude())
    assert turn[first - 1] > 1.0 and turn[first - 2] > 0.1
    assert np.all(np.diff(turn) > -1e-6)   # the arm sinks deeper every frame: the turn only grows


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


def test_penetration_of_several_shapes_at_once_is_one_clear_error(body):
    with pytest.raises(InputError, match="arm_torso_penetration takes one body shape"):
        arm_torso_penetration(_arms_down_clip([90.0]), body, betas=np.zeros((2, 10)))


def test_several_shapes_are_all_cleared(body):
    # beta 2 = +2 widens the hips: arms that hang clear of the mean body sink into it. Turned for
    # both shapes, the arms clear both, and by more than the mean body alone needs.
    wide = np.zeros(body.num_betas)
    wide[2] = 2.0
    clip = _arms_down_clip([75.0, 85.0, 95.0])
    assert arm_torso_penetration(clip, body, betas=wide)["left"].max() > arm_torso_penetration(clip, body)["left"].max()
    both = separate_arms(clip, body, betas=np.stack([np.zeros(body.num_betas), wide]), smooth_s=0.0)
    mean_only = separate_arms(clip, body, smooth_s=0.0)
    for shape in (np.zeros(body.num_betas), wide):
        after = arm_torso_penetration(both, body, betas=shape)
        assert after["left"].max() == 0.0 and after["right"].max() == 0.0
    turn = [fixed.meta["history"][-1]["arms"]["left"]["max_turn_deg"] for fixed in (mean_only, both)]
    assert turn[1] > turn[0]
