"""The agent as a `Policy`: the adapter hands the agent its API dicts, declares its features and returns its
predictions as step details."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from openfly_agent import constants as C
from openfly_agent.rollout.agent import AgentPolicy
from openfly_agent.rollout.policy import OBS_STEP, OBS_TARGET_BOX, PolicyFeatures


def _obs(episode_id: str, rgb: np.ndarray, **extra) -> dict:
    obs = {
        C.EPISODE_ID: episode_id, C.OBS_INSTRUCTION: "fly to the red tower", C.OBS_RGB: rgb,
        C.OBS_POSE: np.array([1.0, 2.0, 3.0, 0.5]), OBS_STEP: 4,
    }  # fmt: skip
    return {**obs, **extra}


def test_the_adapter_passes_the_agent_api_dicts():
    class ScriptedAgent:  # stands in for OpenFlyAgent's select_action / reset API
        def __init__(self):
            self.calls, self.resets = [], []

        def reset(self, ids):
            self.resets.append(ids)

        def select_action(self, observations):
            self.calls.append(observations)
            return [C.ACTION_TURN_LEFT]

    agent = ScriptedAgent()
    policy = AgentPolicy(agent)
    assert policy.features == PolicyFeatures(frames=True, target_box=False, step_details=True)
    policy.reset(["embedded-0/dagger/3"])
    rgb = np.zeros((8, 8, 3), np.uint8)
    assert policy.act([_obs("embedded-0/dagger/3", rgb)]) == [C.ACTION_TURN_LEFT]
    (obs,) = agent.calls[0]
    assert agent.resets == [["embedded-0/dagger/3"]]
    assert set(obs) == {
        C.EPISODE_ID,
        C.OBS_INSTRUCTION,
        C.OBS_RGB,
        C.OBS_POSE,
    }  # the agent's API, nothing more
    assert obs[C.OBS_RGB] is rgb and obs[C.OBS_POSE].tolist() == [1.0, 2.0, 3.0, 0.5]
    with pytest.raises(ValueError, match="no predict_step"):
        AgentPolicy(agent, true_boxes=True)


def test_true_boxes_reach_the_agent_and_its_predictions_are_the_step_details():
    class BoxAgent:  # predict_step: an action and a landmark box per observation
        def __init__(self):
            self.true_boxes = None

        def reset(self, ids):
            pass

        def predict_step(self, observations, true_boxes=None):
            self.true_boxes = true_boxes
            return [
                SimpleNamespace(action=C.ACTION_FORWARD, box=(0.25, 0.5, 0.1, 0.2), box_visible=True),
                SimpleNamespace(action=C.ACTION_STOP, box=(0.0, 0.0, 0.0, 0.0), box_visible=False),
            ]

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
        {"box": None, "keyframes": None},
        {"box": [0.25, 0.5, 0.1, 0.2], "keyframes": None},  # this agent keeps no memory bank
    ]
    policy.reset(["a"])
    assert policy.step_details(["a"]) == [{}]
