"""The agent as a `Policy`: the adapter hands the agent its API dicts, declares its features and returns its
predictions as step details."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from openfly_agent import constants as C
from openfly_agent.rollout.agent import AgentPolicy
from openfly_agent.rollout.policy import OBS_STEP, OBS_TARGET_BOX, PolicyFeatures


def _obs(episode_id: str, rgb: np.ndarray, **extra) -> dict:
    obs = {
        C.EPISODE_ID: episode_id, C.OBS_INSTRUCTION: "fly to the red tower", C.OBS_RGB: rgb,
        C.OBS_POSE: np.array([1.0, 2.0, 3.0, 0.5]), OBS_STEP: 4,
    }  # fmt: skip
    return {**obs, **extra}


def _result(action, box=(0.0, 0.0, 0.0, 0.0), visible=False, sets=()):
    """A `StepResult` as the session returns it (the fields the adapter reads)."""
    return SimpleNamespace(action=action, box=box, box_visible=visible, memory_sets=list(sets))


def test_the_adapter_passes_the_agent_api_dicts():
    class ScriptedSession:  # stands in for AgentSession's predict_step / reset
        def __init__(self):
            self.calls, self.resets, self.true_boxes = [], [], "unset"

        def reset(self, ids):
            self.resets.append(ids)

        def predict_step(self, observations, true_boxes=None):
            self.calls.append(observations)
            self.true_boxes = true_boxes
            return [_result(C.ACTION_TURN_LEFT, sets=[(0,), (3, 4)])]

    session = ScriptedSession()
    policy = AgentPolicy(session)
    assert policy.features == PolicyFeatures(frames=True, target_box=False, step_details=True)
    policy.reset(["embedded-0/dagger/3"])
    rgb = np.zeros((8, 8, 3), np.uint8)
    assert policy.act([_obs("embedded-0/dagger/3", rgb)]) == [C.ACTION_TURN_LEFT]
    (obs,) = session.calls[0]
    assert session.resets == [["embedded-0/dagger/3"]] and session.true_boxes is None
    assert set(obs) == {
        C.EPISODE_ID,
        C.OBS_INSTRUCTION,
        C.OBS_RGB,
        C.OBS_POSE,
    }  # the agent's API, nothing more
    assert obs[C.OBS_RGB] is rgb and obs[C.OBS_POSE].tolist() == [1.0, 2.0, 3.0, 0.5]
    assert policy.step_details(["embedded-0/dagger/3"]) == [{"box": None, "keyframes": [[0], [3, 4]]}]


def test_true_boxes_reach_the_agent_and_its_predictions_are_the_step_details():
    class BoxAgent:  # predict_step: an action and a landmark box per observation
        def __init__(self):
            self.true_boxes = None

        def reset(self, ids):
            pass

        def predict_step(self, observations, true_boxes=None):
            self.true_boxes = true_boxes
            return [_result(C.ACTION_FORWARD, (0.25, 0.5, 0.1, 0.2), True), _result(C.ACTION_STOP)]

    agent = BoxAgent()
    policy = AgentPolicy(agent, "agent_true_box", true_boxes=True)
    assert policy.features.target_box and policy.name == "agent_true_box"
    rgb = np.zeros((8, 8, 3), np.uint8)
    observations = [
        _obs("a", rgb, **{OBS_TARGET_BOX: [0.5, 0.5, 0.3, 0.3]}),
        _obs("b", rgb, **{OBS_TARGET_BOX: None}),
    ]
    assert policy.act(observations) == [C.ACTION_FORWARD, C.ACTION_STOP]
    assert agent.true_boxes == [[0.5, 0.5, 0.3, 0.3], None]
    assert policy.step_details(["b", "a"]) == [
        {"box": None, "keyframes": []},
        {"box": [0.25, 0.5, 0.1, 0.2], "keyframes": []},  # no keyframe set in memory yet
    ]
    policy.reset(["a"])
    assert policy.step_details(["a"]) == [{}]
