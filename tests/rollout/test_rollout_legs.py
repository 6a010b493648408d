"""The current leg's true box on a chained route: the leg moves on within the radius of each leg's goal, and the
policies that read the true box are handed that leg's target's box."""

from __future__ import annotations

import numpy as np
import pytest

from openfly_agent import constants as C
from openfly_agent.data.schema import Episode
from openfly_agent.rollout.legs import CurrentLegBox, current_leg
from openfly_agent.rollout.policy import OBS_STEP, OBS_TARGET_BOX, PolicyFeatures
from openfly_agent.rollout.runner import LockstepRunner
from openfly_agent.sim.base import Observation
from openfly_agent.sim.free_flight import FreeFlightSimulator
from openfly_agent.sim.vector import VectorSimulator

BOXES = {"a": (0.2, 0.5, 0.1, 0.1), "b": (0.5, 0.5, 0.2, 0.2), "c": (0.8, 0.4, 0.1, 0.3)}


def test_the_leg_moves_on_at_each_goal_within_the_radius_never_past_the_last():
    goals = np.array([[0.0, 0.0, 10.0], [40.0, 0.0, 10.0], [100.0, 0.0, 10.0]])
    at = np.array
    assert current_leg(0, at([25.0, 0.0, 10.0]), goals, 20.0) == 0  # 25 m from leg 0's goal
    assert current_leg(0, at([19.0, 0.0, 10.0]), goals, 20.0) == 1  # 19 m from goal 0, 21 m from goal 1
    assert (
        current_leg(0, at([20.0, 0.0, 10.0]), goals, 20.0) == 2
    )  # 20 m from both (inclusive): moved on twice
    assert current_leg(2, at([100.0, 0.0, 10.0]), goals, 20.0) == 2  # the last leg stays
    assert current_leg(1, at([0.0, 0.0, 10.0]), goals, 5.0) == 1  # never back to an earlier leg
    assert current_leg(0, at([0.0, 0.0, 40.0]), goals, 20.0) == 0  # 3-D distance: 30 m above the goal


class ForwardReader:
    """Flies forward 9 m at every step and keeps the true box it was handed."""

    name = "forward_reader"
    features = PolicyFeatures(frames=True, target_box=True)

    def __init__(self):
        self.seen = []

    def reset(self, episode_ids):
        pass

    def act(self, observations):
        self.seen += [(o[OBS_STEP], o[OBS_TARGET_BOX]) for o in observations]
        return [C.ACTION_FORWARD_9] * len(observations)


def _route(leg_goals=None, landmark_ids=("a", "b", "c")) -> Episode:
    """Start at the origin heading +x; goals 27 and 54 m ahead, the last 200 m ahead."""
    return Episode(
        episode_id="synthetic/legs/0",
        scene_id="synthetic",
        instruction="fly past a, then b, to c",
        actions=[C.ACTION_STOP],
        positions=[[0.0, 0.0, 10.0]],
        yaws=[0.0],
        frame_ids=["0"],
        landmark_ids=list(landmark_ids),
        goal=np.array([200.0, 0.0, 10.0]),
        leg_goals=leg_goals,
    )


def _fly(episode, steps, hook):
    def render(scene_id, pose, pitch_deg):
        return Observation(rgb=np.zeros((2, 2, 3), np.uint8), pose=pose, boxes=dict(BOXES))

    policy = ForwardReader()
    with VectorSimulator(sims=[FreeFlightSimulator(render)]) as env:
        LockstepRunner(policy, env, steps, [hook], show_progress=False).run([episode], C.SPLIT_TEST_UNSEEN)
    return policy.seen


def test_the_policy_is_handed_the_box_of_the_current_legs_target():
    """Forward 9 m a step: x = 0, 9, 18, 27, ...; leg 0's goal (x = 27) comes within 20 m at x = 9, leg 1's (x = 54)
    at x = 36; the final box never shows, although every target is in every frame."""
    goals = np.array([[27.0, 0.0, 10.0], [54.0, 0.0, 10.0], [200.0, 0.0, 10.0]])
    seen = _fly(_route(goals), 6, CurrentLegBox())
    a, b, c = (list(BOXES[k]) for k in "abc")
    assert seen == [(0, a), (1, b), (2, b), (3, b), (4, c), (5, c)]
    tight = _fly(
        _route(goals), 6, CurrentLegBox(radius_m=3.0)
    )  # reached only where the drone passes the goal
    assert [box for _, box in tight] == [a, a, a, b, b, b]


def test_a_route_without_each_legs_goal_is_refused():
    with pytest.raises(
        ValueError, match="needs one goal per target landmark .* got 3 targets and no leg goals"
    ):
        _fly(_route(None), 3, CurrentLegBox())
    with pytest.raises(ValueError, match="radius_m=0.0 must be > 0"):
        CurrentLegBox(radius_m=0.0)
