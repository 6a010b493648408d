"""The trained agent as a `Policy`: batched closed-loop inference with per-episode memory, plus its predictions.

`AgentPolicy` is the one place that calls the agent's closed-loop inference API (`predict_step`, or
`select_action(list[dict]) -> list[int]`, and `reset(episode_ids)`); evaluation and DAgger both hold it.
"""

from __future__ import annotations

from openfly_agent import constants as C
from openfly_agent.rollout.policy import OBS_EPISODE_ID, OBS_TARGET_BOX, PolicyFeatures


class AgentPolicy:
    """Adapter from the agent's inference API to the runner's `Policy` protocol.

    Args:
        agent: an `OpenFlyAgent` (or anything with `select_action`, `reset`).
        name: the policy name in tables and folders.
        true_boxes: feed the simulator's true target box to the agent in place of its grounding head's
            (`agent_true_box`: the agent with perfect grounding; the runner adds `target_box` to observations).
    """

    def __init__(self, agent, name: str = "agent", true_boxes: bool = False):
        if true_boxes and not hasattr(agent, "predict_step"):
            raise ValueError(f"{name}: the agent has no predict_step to take true boxes")
        self.agent = agent
        self.name = name
        self.features = PolicyFeatures(frames=True, target_box=true_boxes, step_details=True)
        self._details: dict[str, dict] = {}

    def reset(self, episode_ids: list[str]) -> None:
        self.agent.reset(list(episode_ids))
        for episode_id in episode_ids:
            self._details.pop(episode_id, None)

    def act(self, observations: list[dict]) -> list[int]:
        import torch

        inputs = [
            {key: obs[key] for key in (OBS_EPISODE_ID, C.OBS_INSTRUCTION, C.OBS_RGB, C.OBS_POSE)}
            for obs in observations
        ]
        with torch.inference_mode():
            if not hasattr(self.agent, "predict_step"):
                return [int(a) for a in self.agent.select_action(inputs)]
            if self.features.target_box:
                results = self.agent.predict_step(inputs, [obs[OBS_TARGET_BOX] for obs in observations])
            else:
                results = self.agent.predict_step(inputs)
        for obs, result in zip(inputs, results):
            self._details[obs[OBS_EPISODE_ID]] = self._step_detail(obs[OBS_EPISODE_ID], result)
        return [int(result.action) for result in results]

    def step_details(self, episode_ids: list[str]) -> list[dict]:
        """The predicted landmark box (None when predicted invisible) and the keyframe sets in memory."""
        return [self._details.get(episode_id, {}) for episode_id in episode_ids]

    def _step_detail(self, episode_id: str, result) -> dict:
        """`box`: (cx, cy, w, h) or None; `keyframes`: frame indices of the keyframe sets in the agent memory."""
        box = [float(v) for v in result.box] if getattr(result, "box_visible", False) else None
        state = getattr(self.agent, "episodes", {}).get(episode_id)
        memory = getattr(state, "memory", None)
        if memory is None:
            return {"box": box, "keyframes": None}
        sets = memory.keys()  # MemoryBank keys: one tuple of frame indices per keyframe set, oldest first
        return {"box": box, "keyframes": [[int(i) for i in frames] for frames in sets]}
