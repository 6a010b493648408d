"""The trained agent as a `Policy`: batched closed-loop inference with per-episode memory, plus its predictions.

`AgentPolicy` is the one place that calls the agent's closed-loop inference: an `AgentSession`
(model/session.py, `agent.new_session()`) with `predict_step(observations, true_boxes)` and `reset(episode_ids)`;
evaluation and DAgger both hold it.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, Protocol

from openfly_agent import constants as C
from openfly_agent.rollout.policy import OBS_EPISODE_ID, OBS_TARGET_BOX, PolicyFeatures


class ClosedLoopSession(Protocol):
    """What `AgentPolicy` drives: `model.AgentSession`, or a scripted stand-in in tests."""

    def reset(self, episode_ids: list[str]) -> None: ...

    def predict_step(self, observations: list[dict], true_boxes: Sequence | None = None) -> list[Any]:
        """One result per observation with `action`, `box`, `box_visible` and `memory_sets` (model/episode.py's
        `StepResult`)."""
        ...


class AgentPolicy:
    """Adapter from the agent's session to the runner's `Policy` protocol.

    Args:
        session: the agent's closed-loop session (`agent.new_session()`).
        name: the policy name in tables and folders.
        true_boxes: feed the simulator's true target box to the agent in place of its grounding head's
            (`agent_true_box`: the agent with perfect grounding; the runner adds `target_box` to observations).
    """

    def __init__(self, session: ClosedLoopSession, name: str = "agent", true_boxes: bool = False):
        self.session = session
        self.name = name
        self.features = PolicyFeatures(frames=True, target_box=true_boxes, step_details=True)
        self._details: dict[str, dict] = {}

    def reset(self, episode_ids: list[str]) -> None:
        self.session.reset(list(episode_ids))
        for episode_id in episode_ids:
            self._details.pop(episode_id, None)

    def act(self, observations: list[dict]) -> list[int]:
        import torch

        inputs = [
            {key: obs[key] for key in (OBS_EPISODE_ID, C.OBS_INSTRUCTION, C.OBS_RGB, C.OBS_POSE)}
            for obs in observations
        ]
        true_boxes = [obs[OBS_TARGET_BOX] for obs in observations] if self.features.target_box else None
        with torch.inference_mode():
            results = self.session.predict_step(inputs, true_boxes)
        for obs, result in zip(inputs, results):
            self._details[obs[OBS_EPISODE_ID]] = _step_detail(result)
        return [int(result.action) for result in results]

    def step_details(self, episode_ids: list[str]) -> list[dict]:
        """The predicted landmark box (None when predicted invisible) and the keyframe sets in memory."""
        return [self._details.get(episode_id, {}) for episode_id in episode_ids]


def _step_detail(result) -> dict:
    """`box`: (cx, cy, w, h) or None; `keyframes`: frame indices of each keyframe set in the episode's memory after
    the step, oldest first."""
    box = [float(v) for v in result.box] if result.box_visible else None
    return {"box": box, "keyframes": [[int(i) for i in frames] for frames in result.memory_sets]}
