"""The true box of the current leg's target on a chained route: a runner hook for the policies that read the true box.

`box_servo` and `agent_true_box` are handed the simulator's box of the route's final target by default (what the
released labels hold). On a chained route (the long-route benchmark, `render.box_target: leg`) the agent was
trained on the box of the target of the leg each frame belongs to, so the diagnostic that asks "does the agent fly
when it knows which landmark it is flying to" needs that box in closed loop. `CurrentLegBox` tracks the leg: it
starts at the first and moves on at the first state within `radius_m` of the current leg's goal
(`Episode.leg_goals`), the last leg staying to the end. The radius is the task's success radius by default: a
policy counts as having reached a leg where it would count as having reached the goal.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from openfly_agent import constants as C
from openfly_agent.rollout.policy import OBS_TARGET_BOX
from openfly_agent.rollout.runner import RolloutHook, RunningEpisode

_LEG = "current_leg"  # CurrentLegBox's key in RunningEpisode.state


def current_leg(leg: int, position: np.ndarray, leg_goals: Sequence[np.ndarray], radius_m: float) -> int:
    """The leg after reaching `position` on `leg`: each next goal within `radius_m` moves it on (never past the
    last leg; the A* expert moves on the same way, within its tolerance). E.g. goals 10 m apart along x and a
    radius of 20 m: at x = 0 on leg 0 -> leg 2 of 3."""
    while leg < len(leg_goals) - 1 and float(np.linalg.norm(position - leg_goals[leg])) <= radius_m:
        leg += 1
    return leg


class CurrentLegBox(RolloutHook):
    """Replaces the true target box in each observation (`target_box`) by the box of the current leg's target.

    Needs episodes with one goal per target landmark (`leg_goals`, written by the toolchain); the leg of every
    step goes to `running.state["current_leg"]`.
    """

    def __init__(self, radius_m: float = C.SUCCESS_RADIUS_M):
        if radius_m <= 0:
            raise ValueError(f"radius_m={radius_m} must be > 0")
        self.radius_m = float(radius_m)

    def on_episode_start(self, running: RunningEpisode) -> None:
        episode = running.episode
        if episode.leg_goals is None or len(episode.leg_goals) != len(episode.landmark_ids):
            raise ValueError(
                f"{episode.episode_id}: the current leg's box needs one goal per target landmark (`leg_goals`, "
                f"in datasets generated since the field exists), got {len(episode.landmark_ids)} targets and "
                f"{'no' if episode.leg_goals is None else len(episode.leg_goals)} leg goals"
            )
        running.state[_LEG] = 0

    def before_act(self, running: RunningEpisode) -> bool:
        running.state[_LEG] = current_leg(
            running.state[_LEG], running.obs.pose.position, running.episode.leg_goals, self.radius_m
        )
        return False

    def observation_fields(self, running: RunningEpisode) -> dict:
        return {OBS_TARGET_BOX: running.landmark_box(running.episode.landmark_ids[running.state[_LEG]])}
