"""What a running episode keeps between steps, and what one inference step returns.

Plain data used by `AgentSession` (model/session.py), which owns one `EpisodeState` per episode id; its memory
is an `EpisodeMemory` of the network's memory encoding (model/memory/encoding.py). Nothing here runs a network.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import torch

from openfly_agent.constants import EPISODE_ID, OBS_INSTRUCTION, OBS_RGB

Box = tuple[float, float, float, float]  # (cx, cy, w, h), normalised to [0, 1]


class EpisodeMemory(ABC):
    """What one running episode keeps of its past frames (made by the memory encoding's `new_episode`)."""

    @abstractmethod
    def sets(self) -> list[tuple[int, ...]]:
        """Frame indices of the keyframe sets in memory, oldest first (none for the history encoding)."""


@dataclass
class EpisodeState:
    """One running episode: its prompt, its memory and the history the keyframe selector reads."""

    instruction: str
    prompt_ids: list[int]  # [BOS] prompt (+ suffix), from the processor, once per episode
    memory: EpisodeMemory  # of the network's memory encoding
    actions: list[int] = field(default_factory=list)  # action chosen at each past frame
    boxes: list[Box | None] = field(
        default_factory=list
    )  # predicted box of each past frame; None = invisible

    @property
    def step(self) -> int:
        """Index of the next frame."""
        return len(self.actions)

    @property
    def box_areas(self) -> list[float | None]:
        """Predicted box area of each past frame (fraction of the image), None where invisible."""
        return [None if box is None else box[2] * box[3] for box in self.boxes]

    def record(self, action: int, box: Box | None) -> int:
        """Append the current frame's action and predicted box (None: invisible); returns the frame index."""
        self.actions.append(int(action))
        self.boxes.append(box)
        return self.step - 1


@dataclass
class StepResult:
    """One episode's outcome of `AgentSession.predict_step`."""

    action: int
    action_logits: torch.Tensor  # discrete: (10,) logits of the action ids; bins: (8,) generated token ids
    box: Box  # predicted landmark box (cx, cy, w, h)
    box_visible: bool
    memory_sets: list[
        tuple[int, ...]
    ]  # frame indices of the keyframe sets in memory after the step, oldest first


def check_observations(observations: Sequence[dict[str, Any]]) -> None:
    """Each observation names its episode, instruction and frame; no episode appears twice in one step."""
    ids = []
    for index, obs in enumerate(observations):
        missing = {EPISODE_ID, OBS_INSTRUCTION, OBS_RGB} - set(obs)
        if missing:
            raise ValueError(f"observation {index} lacks {sorted(missing)} (episode_id, instruction, rgb)")
        ids.append(obs[EPISODE_ID])
    if len(set(ids)) != len(ids):
        raise ValueError(f"an episode appears twice in one select_action call: {ids}")
