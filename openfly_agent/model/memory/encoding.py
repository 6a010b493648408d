"""The memory encoding's interface: what the network remembers of past frames, in training and online.

Two encodings implement it, chosen once from the config by `make_memory_encoding` (model/factory.py):
`KeyframeMemory` (model/memory/keyframe_memory.py: keyframe sets merged into their largest-box frame,
grid-pooled, projected) and `HistoryMemory` (model/memory/history_memory.py: the OpenVLA-compatible history, one
token per past frame). They run the network's vision backbone and projector, passed in by the network
(model/network.py).
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import Any

import torch
from torch import nn

from openfly_agent.constants import MEMORY_FRAME_MASK, MEMORY_PIXEL_VALUES
from openfly_agent.model.episode import EpisodeMemory, EpisodeState


@dataclass
class StepFrames:
    """The current frames of one closed-loop step, once encoded (one row per episode)."""

    patches: torch.Tensor  # (B, P, D_v) backbone features
    dino_cls: torch.Tensor | None  # (B, D_dino) DINO CLS tokens; None for the CNN
    current: torch.Tensor  # (B, P, D) projected tokens, as they enter the LLM


def memory_frames(batch: dict[str, Any]) -> tuple[torch.Tensor, torch.Tensor]:
    """A training batch's memory frames: the (B, K, S) bool mask of the real ones and those (n_real, 3, H, W)
    frames, in the mask's row-major order."""
    pixels = batch[MEMORY_PIXEL_VALUES]  # (B, K, S, 3, H, W)
    frame_mask = batch[MEMORY_FRAME_MASK].bool().to(pixels.device)  # (B, K, S)
    return frame_mask, pixels[frame_mask]


class MemoryEncoding(ABC):
    """Memory tokens of a training batch, and of each running episode before and after its step."""

    @abstractmethod
    def batch_tokens(
        self,
        vision_backbone: nn.Module,
        projector: nn.Module,
        batch: dict[str, Any],
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """(B, M, D) memory tokens of a training batch holding `memory_*` keys, and their (B, M) bool mask."""

    @abstractmethod
    def new_episode(self) -> EpisodeMemory:
        """The empty memory of an episode that starts."""

    @abstractmethod
    def read(
        self,
        vision_backbone: nn.Module,
        projector: nn.Module,
        episodes: list[EpisodeState],
        frames: StepFrames,
    ) -> list[torch.Tensor]:
        """Each episode's (M_i, D) memory tokens at this step, oldest first."""

    @abstractmethod
    def write(self, projector: nn.Module, episodes: list[EpisodeState], frames: StepFrames) -> None:
        """Remember this step's frames (after each episode recorded its action and box)."""
