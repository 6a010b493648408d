import math

import numpy as np
import pytest

from openfly_agent import constants as C
from openfly_agent.sim.dynamics import apply_action, rollout_array, step_motion
from openfly_agent.utils.geometry import Pose, wrap_yaw


@pytest.mark.parametrize(
    "action, expected",
    [
        (C.ACTION_STOP, (0, 0, 10, 0)),
        (C.ACTION_FORWARD, (3, 0, 10, 0)),
        (C.ACTION_FORWARD_6, (6, 0, 10, 0)),
        (C.ACTION_FORWARD_9, (9, 0, 10, 0)),
        (C.ACTION_TURN_LEFT, (0, 0, 10, math.radians(30))),
        (C.ACTION_TURN_RIGHT, (0, 0, 10, -math.radians(30))),
        (C.ACTION_ASCEND, (0, 0, 13, 0)),
        (C.ACTION_DESCEND, (0, 0, 7, 0)),
        (C.ACTION_MOVE_LEFT, (0, 3, 10, 0)),
        (C.ACTION_MOVE_RIGHT, (0, -3, 10, 0)),
        (C.ACTION_TAKEOFF, (0, 0, 13, 0)),
        (C.ACTION_LANDING, (0, 0, 7, 0)),
    ],
)
def test_each_action_from_the_origin_facing_east(action, expected):
    out = apply_action(Pose(0, 0, 10, 0), action)
    np.testing.assert_allclose(out.as_array(), expected, atol=1e-12)


def test_forward_follows_heading_and_lateral_is_perpendicular():
    north = Pose(0, 0, 0, math.pi / 2)
    np.testing.assert_allclose(apply_action(north, C.ACTION_FORWARD).position, [0, 3, 0], atol=1e-12)
    np.testing.assert_allclose(apply_action(north, C.ACTION_MOVE_LEFT).position, [-3, 0, 0], atol=1e-12)


def test_yaw_wraps_to_minus_pi_pi():
    pose = Pose(0, 0, 0, math.radians(170))
    assert apply_action(pose, C.ACTION_TURN_LEFT).yaw == pytest.approx(math.radians(-160))
    assert wrap_yaw(math.pi) == pytest.approx(math.pi)
    assert wrap_yaw(-math.pi) == pytest.approx(math.pi)


def test_twelve_left_turns_come_back():
    poses = rollout_array(Pose(1, 2, 3, 0.3), [C.ACTION_TURN_LEFT] * 12)
    assert poses.shape == (13, 4)
    assert wrap_yaw(poses[-1, 3] - 0.3) == pytest.approx(0.0, abs=1e-9)


def test_unknown_action_is_a_clear_error():
    with pytest.raises(ValueError, match="unknown action id 11"):
        apply_action(Pose(0, 0, 0, 0), 11)


def test_motion_segment():
    motion = step_motion(Pose(0, 0, 0, 0), C.ACTION_FORWARD_9)
    assert motion.translation == pytest.approx(9.0)
    assert not motion.is_stop
