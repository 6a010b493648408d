"""What the agent remembers about a running episode, and what one inference step returns.

Plain data used by `OpenFlyAgent.predict_step` (model/agent.py), which owns one `EpisodeState` per episode id
in `agent.episodes`; nothing here runs a network.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import torch

from openfly_agent.constants import EPISODE_ID, OBS_INSTRUCTION, OBS_RGB
from openfly_agent.model.memory.bank import MemoryBank

Box = tuple[float, float, float, float]  # (cx, cy, w, h), normalised to [0, 1]


@dataclass
class EpisodeState:
    """One running episode: its prompt, its memory bank and the history the keyframe selector reads."""

    instruction: str
    prompt_ids: list[int]  # [BOS] prompt (+ suffix), from the processor, once per episode
    memory: MemoryBank  # projected tokens of the last K keyframe sets, oldest first
    actions: list[int] = field(default_factory=list)  # action chosen at each past frame
    boxes: list[Box | None] = field(
        default_factory=list
    )  # predicted box of each past frame; None = invisible
    frame_features: dict[int, torch.Tensor] = field(default_factory=dict)  # recent frames: (P, D_v)
    history_tokens: dict[int, torch.Tensor] = field(default_factory=dict)  # openvla_compat: frame -> (D,)

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

    def keep_history_token(self, frame: int, token: torch.Tensor, capacity: int) -> None:
        """openvla_compat: store frame `frame`'s (D,) history token; keep frame 0 and the last `capacity` only."""
        self.history_tokens[frame] = token
        keep = {0, *range(self.step - capacity, self.step)}
        self.history_tokens = {i: t for i, t in self.history_tokens.items() if i in keep}

    def compat_history(self, own: torch.Tensor, capacity: int) -> torch.Tensor:
        """openvla_compat: the (K, D) history tokens of the released model's 3-image input at this step (`own`:
        the current frame's token, the padding of the first step)."""
        if self.step == 0:
            tokens = [own] * capacity
        else:
            tokens = [self.history_tokens[i] for i in compat_history_indices(self.step, capacity)]
        return torch.stack(tokens) if tokens else own.new_zeros(0, own.shape[-1])

    def forget_features_before(self, frame: int) -> None:
        """Drop encoded features of frames before `frame` (no keyframe set that can still complete needs them)."""
        for index in [i for i in self.frame_features if i < frame]:
            del self.frame_features[index]


@dataclass
class StepResult:
    """One episode's outcome of `OpenFlyAgent.predict_step`."""

    action: int
    action_logits: torch.Tensor  # discrete: (10,) logits of the action ids; bins: (8,) generated token ids
    box: Box  # predicted landmark box (cx, cy, w, h)
    box_visible: bool


def compat_history_indices(step: int, count: int) -> list[int]:
    """Frames shown as history by the released model at `step`: t-count .. t-1 clipped at 0 (eval pads
    by repeating the first frame: [f0, f0, f0], [f0, f0, f1], then [t-2, t-1, t])."""
    return [max(0, step - count + i) for i in range(count)]


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
