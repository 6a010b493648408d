"""The OpenVLA-compatible history (`memory.encoding.type: openvla_history`, the released model's layout): one token
per past frame, DINO CLS ++ grid-pooled SigLIP patches, projected; online, the released model's 3-image input padded
with the first frame."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import torch
from torch import nn

from openfly_agent.model.config import HistoryEncodingConfig, ModelConfig
from openfly_agent.model.episode import EpisodeMemory, EpisodeState
from openfly_agent.model.memory.encoding import MemoryEncoding, StepFrames, memory_frames
from openfly_agent.model.memory.keyframes import KeyframeSelector
from openfly_agent.model.memory.merging import grid_pool


@dataclass
class HistoryEpisodeMemory(EpisodeMemory):
    """One episode's history tokens: frame 0 (the padding of early steps) and the last K frames."""

    tokens: dict[int, torch.Tensor] = field(default_factory=dict)  # frame -> (D,)
    current: torch.Tensor | None = None  # (D,) the token of the frame of the running step

    def __len__(self) -> int:
        return len(self.tokens)

    def sets(self) -> list[tuple[int, ...]]:
        return []


def history_indices(step: int, count: int) -> list[int]:
    """Frames shown as history by the released model at `step`: t-count .. t-1 clipped at 0 (eval pads
    by repeating the first frame: [f0, f0, f0], [f0, f0, f1], then [t-2, t-1, t])."""
    return [max(0, step - count + i) for i in range(count)]


class HistoryMemory(MemoryEncoding):
    """Past frames -> one token each (`memory.capacity` frames, `memory.grid` pooling, LLM width `llm_dim`)."""

    def __init__(self, capacity: int, grid: int, llm_dim: int) -> None:
        self.capacity, self.grid, self.llm_dim = capacity, grid, llm_dim

    def frame_tokens(
        self, vision_backbone: nn.Module, projector: nn.Module, patches: torch.Tensor, dino_cls: torch.Tensor
    ) -> torch.Tensor:
        """(N, P, D_v) fused patches, (N, D_dino) CLS -> (N, D_llm): DINO CLS ++ pooled SigLIP patches, projected."""
        siglip = patches[..., vision_backbone.dino_dim :]  # (N, P, D_siglip)
        pooled = grid_pool(siglip, self.grid)[:, 0]  # (N, D_siglip)
        return projector(torch.cat([dino_cls, pooled], dim=-1))  # (N, D)

    def batch_tokens(
        self,
        vision_backbone: nn.Module,
        projector: nn.Module,
        batch: dict[str, Any],
    ) -> tuple[torch.Tensor, torch.Tensor]:
        frame_mask, real = memory_frames(batch)  # (B, K, S), (n_real, 3, H, W)
        b, k, s = frame_mask.shape
        tokens = projector.fc3.weight.new_zeros(b, k * s, self.llm_dim)  # (B, K*S, D)
        if real.shape[0]:
            tokens[frame_mask.view(b, k * s)] = self.frame_tokens(
                vision_backbone, projector, *vision_backbone.forward_with_cls(real)
            )
        return tokens, frame_mask.view(b, k * s)

    def new_episode(self) -> HistoryEpisodeMemory:
        return HistoryEpisodeMemory()

    def read(
        self,
        vision_backbone: nn.Module,
        projector: nn.Module,
        episodes: list[EpisodeState],
        frames: StepFrames,
    ) -> list[torch.Tensor]:
        """The (K, D) history of each episode; the current frame's own token pads the first step."""
        own = self.frame_tokens(vision_backbone, projector, frames.patches, frames.dino_cls)  # (B, D)
        history = []
        for row, episode in enumerate(episodes):
            episode.memory.current = own[row]
            if episode.step == 0:
                tokens = [own[row]] * self.capacity
            else:
                tokens = [episode.memory.tokens[i] for i in history_indices(episode.step, self.capacity)]
            history.append(torch.stack(tokens) if tokens else own.new_zeros(0, own.shape[-1]))
        return history

    def write(self, projector: nn.Module, episodes: list[EpisodeState], frames: StepFrames) -> None:
        """Keep the step's frame token; only frame 0 and the last `capacity` frames stay."""
        for episode in episodes:
            memory = episode.memory
            memory.tokens[episode.step - 1] = memory.current
            keep = {0, *range(episode.step - self.capacity, episode.step)}
            memory.tokens = {i: t for i, t in memory.tokens.items() if i in keep}
            memory.current = None


@HistoryEncodingConfig.register_builder
def _history_memory(
    encoding: HistoryEncodingConfig, cfg: ModelConfig, selector: KeyframeSelector
) -> HistoryMemory:
    return HistoryMemory(cfg.memory.capacity, cfg.memory.grid, cfg.llm.hidden_size)  # no keyframe selection
