"""`box_servo`: the reflex reference policy, handed the TRUE box of the target landmark at every step.

It never sees a map or the instruction, only where the target is in the frame (the embedded simulator's
instance-buffer box of `episode.landmark_ids[-1]`), so the gap between it and a learned agent measures what the
agent's perception misses. The rule (defaults measured on embedded-small, docs/EVAL.md):

- target not visible: turn left (search) for up to `search_steps` steps in a row, then fly forward 9 m;
- box centre more than `center_band` of the image width from the centre: turn toward it (a 30 degree turn
  moves a box by about a third of the 90 degree frame, so a narrower band oscillates);
- box area >= `stop_area`: STOP; area < `far_area`: forward 9 m; otherwise forward 3 m.
"""

from __future__ import annotations

from dataclasses import dataclass

from openfly_agent import constants as C
from openfly_agent.rollout.policy import OBS_EPISODE_ID, OBS_TARGET_BOX, PolicyFeatures


@dataclass
class BoxServoSettings:
    """Thresholds of the reflex rule (fractions of the image width / area)."""

    center_band: float = 0.22  # |cx - 0.5| above this: turn toward the box
    stop_area: float = 0.45  # box area (w * h) at which it stops
    far_area: float = 0.15  # below this area it flies 9 m, else 3 m
    search_steps: int = 12  # left turns in a row while the target is not visible, then forward 9 m

    def __post_init__(self) -> None:
        if not 0.0 <= self.center_band < 0.5:
            raise ValueError(f"box_servo.center_band={self.center_band} must be in [0, 0.5)")
        if not 0.0 < self.far_area <= self.stop_area <= 1.0:
            raise ValueError(
                f"box_servo: need 0 < far_area ({self.far_area}) <= stop_area ({self.stop_area}) <= 1"
            )
        if self.search_steps < 0:
            raise ValueError(f"box_servo.search_steps={self.search_steps} must be >= 0")


def servo_action(box, settings: BoxServoSettings, steps_unseen: int) -> int:
    """The rule's action for one frame.

    Args:
        box: (cx, cy, w, h) of the target in [0, 1], or None when it is not visible.
        settings: the thresholds.
        steps_unseen: consecutive earlier steps of this episode without the target in view.
    """
    if box is None:
        return C.ACTION_TURN_LEFT if steps_unseen < settings.search_steps else C.ACTION_FORWARD_9
    cx, _, w, h = (float(v) for v in box)
    if abs(cx - 0.5) > settings.center_band:
        return C.ACTION_TURN_LEFT if cx < 0.5 else C.ACTION_TURN_RIGHT
    area = w * h
    if area >= settings.stop_area:
        return C.ACTION_STOP
    return C.ACTION_FORWARD_9 if area < settings.far_area else C.ACTION_FORWARD


class BoxServoPolicy:
    """The reflex rule as a batched `Policy`; the runner adds `target_box` to each observation."""

    name = "box_servo"
    # rendered observations (their instance boxes, though not the pixels) and the true target box
    features = PolicyFeatures(frames=True, target_box=True)

    def __init__(self, settings: BoxServoSettings | None = None):
        self.settings = settings or BoxServoSettings()
        self._unseen: dict[str, int] = {}

    def reset(self, episode_ids: list[str]) -> None:
        for episode_id in episode_ids:
            self._unseen.pop(episode_id, None)

    def act(self, observations: list[dict]) -> list[int]:
        actions = []
        for obs in observations:
            if OBS_TARGET_BOX not in obs:
                raise KeyError(
                    "box_servo needs the target landmark's box in every observation (`target_box`): it runs "
                    "in the embedded simulator only"
                )
            episode_id, box = obs[OBS_EPISODE_ID], obs[OBS_TARGET_BOX]
            unseen = self._unseen.get(episode_id, 0)
            actions.append(servo_action(box, self.settings, unseen))
            self._unseen[episode_id] = unseen + 1 if box is None else 0
        return actions
