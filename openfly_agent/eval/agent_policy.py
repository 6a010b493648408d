"""The trained agent as a `Policy`: batched `select_action` with per-episode memory, plus its predictions.

`AgentPolicy` wraps any object with the agent's public inference API (`select_action(list[dict]) ->
list[int]`, `reset(episode_ids)`, optionally `last_step_info`), so the runner never touches model
internals. `load_agent` builds `OpenFlyAgent` from our checkpoint folder, a released OpenVLA /
OpenFly-Agent folder (through the model's `openvla_compat` path and `openvla_bins` head) or a Hub id.
"""

from __future__ import annotations

import logging

from openfly_agent import constants as C
from openfly_agent.eval.policy import OBS_EPISODE_ID

logger = logging.getLogger(__name__)


class AgentPolicy:
    """Adapter from the agent's inference API to the runner's `Policy` protocol.

    Args:
        agent: an `OpenFlyAgent` (or anything with `select_action`, `reset`).
        name: the policy name in tables and folders.
    """

    needs_frames = True

    def __init__(self, agent, name: str = "agent"):
        self.agent = agent
        self.name = name

    def reset(self, episode_ids: list[str]) -> None:
        self.agent.reset(list(episode_ids))

    def act(self, observations: list[dict]) -> list[int]:
        import torch

        inputs = [
            {key: obs[key] for key in (OBS_EPISODE_ID, C.OBS_INSTRUCTION, C.OBS_RGB, C.OBS_POSE)}
            for obs in observations
        ]
        with torch.inference_mode():
            return [int(a) for a in self.agent.select_action(inputs)]

    def step_details(self, episode_ids: list[str]) -> list[dict]:
        """The predicted landmark box and keyframe decision of the last step, per episode (if exposed)."""
        info = getattr(self.agent, "last_step_info", None)
        if not info:
            return [{} for _ in episode_ids]
        return [_details(info.get(episode_id)) for episode_id in episode_ids]


def _details(step: dict | None) -> dict:
    if not step:
        return {}
    out = {}
    box = step.get("box")
    if box is not None:
        out["box"] = [float(v) for v in box]
    if "keyframe" in step:
        out["keyframe"] = bool(step["keyframe"])
    return out
