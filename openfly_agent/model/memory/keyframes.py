"""Keyframe selection (paper: keyframe-aware memory): motion change points -> candidate sets -> area test.

Pure functions over action / pose histories. The dataset calls `KeyframeSelector.select` with ground-truth
box areas, the agent calls it online with predicted ones, so training and inference pick frames alike.

Definitions (docs/ARCHITECTURE.md):
- motion class of an action id: the id itself, except forward 1 / 8 / 9 -> 1 (one motion, different
  lengths; when `merge_forward`), take-off -1 -> ascend 4 and landing -2 -> descend 5;
- frame t >= 1 is a motion change point when its motion class differs from frame t - 1's;
- the candidate set of change point c is frames c - r .. c + r (r = 2), clipped at 0; it is complete at
  step t when c + r <= t - 1 (all its frames are in the past);
- a frame is kept when its landmark box covers >= theta of the image (area = w * h of the normalised box;
  None = landmark not visible = not kept); a set with no kept frame is dropped.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from openfly_agent.constants import (
    ACTION_ASCEND,
    ACTION_DESCEND,
    ACTION_FORWARD,
    ACTION_FORWARD_6,
    ACTION_FORWARD_9,
    ACTION_LANDING,
    ACTION_MOVE_LEFT,
    ACTION_MOVE_RIGHT,
    ACTION_STOP,
    ACTION_TAKEOFF,
    ACTION_TURN_LEFT,
    ACTION_TURN_RIGHT,
)

if TYPE_CHECKING:
    from openfly_agent.model.config import KeyframeConfig

_PHASE_CLASS = {ACTION_TAKEOFF: ACTION_ASCEND, ACTION_LANDING: ACTION_DESCEND}
_FORWARD_IDS = (ACTION_FORWARD, ACTION_FORWARD_6, ACTION_FORWARD_9)


def motion_class(action_id: int, merge_forward: bool = True) -> int:
    """Motion class of an OpenFly action id (forward lengths merged; take-off/landing as ascend/descend)."""
    action_id = int(action_id)
    if merge_forward and action_id in _FORWARD_IDS:
        return ACTION_FORWARD
    return _PHASE_CLASS.get(action_id, action_id)


def change_points(actions: Sequence[int], merge_forward: bool = True) -> list[int]:
    """Frames t >= 1 whose motion class differs from frame t - 1's."""
    classes = [motion_class(a, merge_forward) for a in actions]
    return [t for t in range(1, len(classes)) if classes[t] != classes[t - 1]]


def candidate_set(change_point: int, radius: int) -> list[int]:
    """Frames `change_point - radius .. change_point + radius`, clipped at 0."""
    return list(range(max(0, change_point - radius), change_point + radius + 1))


def motion_classes_from_poses(
    poses: np.ndarray, turn_tol_rad: float = np.deg2rad(5.0), move_tol_m: float = 0.5
) -> list[int]:
    """Motion class of each frame from the pose history (the motion from pose t to pose t + 1).

    For trajectories whose action labels are unreliable (docs/OFFICIAL_OPENFLY.md 1.2: merged forward labels
    sit on the block's last frame). A yaw change beats a height change, which beats a horizontal move; the
    last frame (no next pose) is STOP.

    Args:
        poses: (T, 4) x, y, z, yaw (radians, CCW, any unwrapping).
        turn_tol_rad: smallest yaw change that counts as a turn.
        move_tol_m: smallest displacement that counts as a move.

    Returns:
        T motion classes (action ids 0..7, forward merged).
    """
    poses = np.asarray(poses, dtype=np.float64)
    if poses.ndim != 2 or poses.shape[1] != 4:
        raise ValueError(f"poses must be (T, 4) x, y, z, yaw; got shape {poses.shape}")
    classes = []
    for (x0, y0, z0, yaw0), (x1, y1, z1, yaw1) in zip(poses[:-1], poses[1:]):
        dyaw = np.arctan2(np.sin(yaw1 - yaw0), np.cos(yaw1 - yaw0))
        dx, dy, dz = x1 - x0, y1 - y0, z1 - z0
        along = dx * np.cos(yaw0) + dy * np.sin(yaw0)  # (m) along the heading
        left = -dx * np.sin(yaw0) + dy * np.cos(yaw0)  # (m) to the left
        if abs(dyaw) >= turn_tol_rad:
            classes.append(ACTION_TURN_LEFT if dyaw > 0 else ACTION_TURN_RIGHT)
        elif abs(dz) >= move_tol_m:
            classes.append(ACTION_ASCEND if dz > 0 else ACTION_DESCEND)
        elif abs(along) >= move_tol_m and abs(along) >= abs(left):
            classes.append(ACTION_FORWARD)
        elif abs(left) >= move_tol_m:
            classes.append(ACTION_MOVE_LEFT if left > 0 else ACTION_MOVE_RIGHT)
        else:
            classes.append(ACTION_STOP)
    if len(poses):
        classes.append(ACTION_STOP)
    return classes


@dataclass(frozen=True)
class KeyframeSelector:
    """Selects the keyframe sets that enter the memory at step t.

    Args:
        capacity: K, the number of (most recent) sets returned.
        theta: area threshold as a fraction of the image.
        radius: frames before / after each change point.
        merge_forward: count forward 1 / 8 / 9 as one motion class.
    """

    capacity: int = 2
    theta: float = 0.25
    radius: int = 2
    merge_forward: bool = True

    def __post_init__(self) -> None:
        if self.capacity < 0 or self.radius < 0:
            raise ValueError(
                f"KeyframeSelector: capacity={self.capacity} and radius={self.radius} must be >= 0"
            )
        if not 0.0 <= self.theta <= 1.0:
            raise ValueError(f"KeyframeSelector: theta={self.theta} must be in [0, 1]")

    @classmethod
    def from_config(cls, keyframes: KeyframeConfig, capacity: int) -> KeyframeSelector:
        """The selector of a model's `keyframes` settings and `memory.capacity` (training, inference, benches)."""
        return cls(
            capacity=capacity,
            theta=keyframes.theta,
            radius=keyframes.radius,
            merge_forward=keyframes.merge_forward,
        )

    @property
    def set_size(self) -> int:
        """S, the most frames in one set."""
        return 2 * self.radius + 1

    def completed_sets(self, actions: Sequence[int], t: int) -> list[list[int]]:
        """All candidate sets complete at step t (frames <= t - 1), oldest first, before the area filter."""
        if t < 0 or t > len(actions):
            raise ValueError(f"step t={t} is outside the action history of length {len(actions)}")
        points = change_points(list(actions[:t]), self.merge_forward)
        return [candidate_set(c, self.radius) for c in points if c + self.radius <= t - 1]

    def select(
        self, actions: Sequence[int], box_areas: Sequence[float | None] | None, t: int
    ) -> list[list[int]]:
        """The last K completed, area-filtered keyframe sets at step t (frame indices < t, oldest first).

        Only `actions[:t]` and `box_areas[:t]` are read, so passing a whole episode never leaks the future.

        Args:
            actions: action id of each frame (the action taken from that frame).
            box_areas: landmark box area of each frame as a fraction of the image, None where the
                landmark is not visible. None for the whole argument means boxes are unknown (e.g. the
                released OpenFly data): the area test is skipped and every candidate frame is kept.
            t: the current step; frames < t are history.
        """
        if self.capacity == 0:
            return []
        if box_areas is not None and len(box_areas) < t:
            raise ValueError(f"box_areas has {len(box_areas)} entries, fewer than step t={t}")
        kept_sets = []
        for frames in self.completed_sets(actions, t):
            kept = [f for f in frames if box_areas is None or _passes(box_areas[f], self.theta)]
            if kept:
                kept_sets.append(kept)
        return kept_sets[-self.capacity :]


def _passes(area: float | None, theta: float) -> bool:
    return area is not None and float(area) >= theta
