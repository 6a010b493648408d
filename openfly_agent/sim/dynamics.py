"""The single place where OpenFly action ids become motion (docs/CONVENTIONS.md, 'Actions').

Every step is a teleport, as in the official evaluation: translation along the heading, a lateral
move, a vertical move or a yaw change. `step_motion` also returns the straight segment the drone
sweeps, which the collision check tests against the occupancy grid.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from openfly_agent import constants as C
from openfly_agent.utils.geometry import Pose, wrap_yaw

_TURN_RAD = math.radians(C.TURN_DEGREES)


@dataclass(frozen=True)
class Motion:
    """What one action does: start and end pose and the swept straight segment (start -> end)."""

    start: Pose
    end: Pose
    action: int

    @property
    def translation(self) -> float:
        return self.start.distance_to(self.end)

    @property
    def is_stop(self) -> bool:
        return self.action == C.ACTION_STOP


def _forward(pose: Pose, metres: float) -> Pose:
    return Pose(pose.x + metres * math.cos(pose.yaw), pose.y + metres * math.sin(pose.yaw), pose.z, pose.yaw)


def _lateral(pose: Pose, metres_left: float) -> Pose:
    # Left of heading (cos, sin) is (-sin, cos).
    return Pose(
        pose.x - metres_left * math.sin(pose.yaw),
        pose.y + metres_left * math.cos(pose.yaw),
        pose.z,
        pose.yaw,
    )


def apply_action(pose: Pose, action: int, step: float = C.STEP_METERS) -> Pose:
    """Pose after executing `action` from `pose`. Yaw of the result is wrapped to (-pi, pi]."""
    if action == C.ACTION_STOP:
        new = pose
    elif action == C.ACTION_FORWARD:
        new = _forward(pose, step)
    elif action == C.ACTION_FORWARD_6:
        new = _forward(pose, 2 * step)
    elif action == C.ACTION_FORWARD_9:
        new = _forward(pose, 3 * step)
    elif action == C.ACTION_TURN_LEFT:
        new = Pose(pose.x, pose.y, pose.z, pose.yaw + _TURN_RAD)
    elif action == C.ACTION_TURN_RIGHT:
        new = Pose(pose.x, pose.y, pose.z, pose.yaw - _TURN_RAD)
    elif action in (C.ACTION_ASCEND, C.ACTION_TAKEOFF):
        new = Pose(pose.x, pose.y, pose.z + step, pose.yaw)
    elif action in (C.ACTION_DESCEND, C.ACTION_LANDING):
        new = Pose(pose.x, pose.y, pose.z - step, pose.yaw)
    elif action == C.ACTION_MOVE_LEFT:
        new = _lateral(pose, step)
    elif action == C.ACTION_MOVE_RIGHT:
        new = _lateral(pose, -step)
    else:
        raise ValueError(f"unknown action id {action!r}; valid ids are {sorted(C.ACTION_NAMES)}")
    return Pose(new.x, new.y, new.z, wrap_yaw(new.yaw))


def step_motion(pose: Pose, action: int, step: float = C.STEP_METERS) -> Motion:
    """The motion of one step, with the segment to check for collisions."""
    return Motion(start=pose, end=apply_action(pose, action, step), action=action)


def rollout(start: Pose, actions, step: float = C.STEP_METERS) -> list[Pose]:
    """Poses visited by executing `actions` from `start`: len(actions) + 1 poses, start first."""
    poses = [start]
    for action in actions:
        poses.append(apply_action(poses[-1], int(action), step))
    return poses


def rollout_array(start: Pose, actions, step: float = C.STEP_METERS) -> np.ndarray:
    """`rollout` as a (T + 1, 4) array of (x, y, z, yaw)."""
    return np.stack([p.as_array() for p in rollout(start, actions, step)])
