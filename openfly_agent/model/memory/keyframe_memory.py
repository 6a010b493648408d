"""The keyframe memory (`memory.encoding.type: keyframes`, the default): the last K keyframe sets, each merged into its largest-box frame,
grid-pooled and projected to LLM tokens; online, the sets the keyframe selector picks from the episode so far, kept in
each episode's FIFO `MemoryBank`."""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Hashable
from dataclasses import dataclass, field
from typing import Any

import torch
from torch import nn

from openfly_agent.constants import MEMORY_BOX_VISIBLE, MEMORY_BOXES
from openfly_agent.model.config import KeyframeEncodingConfig, ModelConfig
from openfly_agent.model.episode import EpisodeMemory, EpisodeState
from openfly_agent.model.memory.encoding import MemoryEncoding, StepFrames, memory_frames
from openfly_agent.model.memory.keyframes import KeyframeSelector
from openfly_agent.model.memory.merging import choose_reference, grid_pool, merge_into_reference
from openfly_agent.model.vision.backbone import encode_frames


class MemoryBank:
    """FIFO of at most `capacity` entries (pooled keyframe-set tokens), keyed so a set is stored once.

    Args:
        capacity: K; pushing onto a full bank evicts the oldest entry.
    """

    def __init__(self, capacity: int) -> None:
        if capacity < 0:
            raise ValueError(f"MemoryBank capacity={capacity} must be >= 0")
        self.capacity = capacity
        self._entries: OrderedDict[Hashable, torch.Tensor] = OrderedDict()

    def __len__(self) -> int:
        return len(self._entries)

    def __contains__(self, key: Hashable) -> bool:
        return key in self._entries

    def push(self, key: Hashable, tokens: torch.Tensor) -> list[Hashable]:
        """Append `tokens` under `key` (already stored: no change); returns the evicted keys, oldest first."""
        if self.capacity == 0 or key in self._entries:
            return []
        self._entries[key] = tokens
        evicted = []
        while len(self._entries) > self.capacity:
            evicted.append(self._entries.popitem(last=False)[0])
        return evicted

    def keys(self) -> list[Hashable]:
        """Stored keys, oldest first."""
        return list(self._entries)

    def tokens(self) -> list[torch.Tensor]:
        """Stored token tensors, oldest first."""
        return list(self._entries.values())

    def clear(self) -> None:
        """Forget everything (episode reset)."""
        self._entries.clear()


@dataclass
class KeyframeEpisodeMemory(EpisodeMemory):
    """One episode's bank of keyframe-set tokens and the features of its recent frames."""

    bank: MemoryBank  # projected tokens of the last K keyframe sets, oldest first
    frame_features: dict[int, torch.Tensor] = field(default_factory=dict)  # recent frames: (P, D_v)

    def __len__(self) -> int:
        return len(self.bank)

    def sets(self) -> list[tuple[int, ...]]:
        return list(self.bank.keys())

    def forget_features_before(self, frame: int) -> None:
        """Drop encoded features of frames before `frame` (no keyframe set that can still complete needs them)."""
        for index in [i for i in self.frame_features if i < frame]:
            del self.frame_features[index]


class KeyframeMemory(MemoryEncoding):
    """Keyframe sets -> merged, pooled, projected memory tokens (`memory`, `merging` and `keyframes` sections)."""

    def __init__(self, cfg: ModelConfig, selector: KeyframeSelector) -> None:
        self.capacity = cfg.memory.capacity
        self.grid = cfg.memory.grid
        self.merging = cfg.merging
        self.num_patches, self.feature_dim = cfg.vision.num_patches, cfg.vision.feature_dim
        self.selector = selector

    def set_tokens(
        self,
        projector: nn.Module,
        features: torch.Tensor,
        frame_mask: torch.Tensor,
        boxes: torch.Tensor,
        box_visible: torch.Tensor,
    ) -> torch.Tensor:
        """Keyframe sets -> memory tokens: merge into the largest-box frame, grid-pool, project.

        Args:
            projector: the network's projector (D_v -> D_llm).
            features: (N, S, P, D_v) fused features of each frame of each set.
            frame_mask: (N, S) bool, real frames.
            boxes: (N, S, 4) landmark boxes (ground truth in training, predicted online).
            box_visible: (N, S) bool.

        Returns:
            (N, (sqrt(P) / g)^2, D_llm) tokens.
        """
        reference = choose_reference(boxes.to(features.device), box_visible.to(features.device), frame_mask)
        if self.merging.enabled:
            merged = merge_into_reference(
                features, frame_mask, reference, self.merging.threshold, self.merging.top_r
            )
        else:
            merged = features[
                torch.arange(features.shape[0], device=features.device), reference
            ]  # (N, P, D_v)
        return projector(grid_pool(merged, self.grid))  # (N, m, D)

    def batch_tokens(
        self,
        vision_backbone: nn.Module,
        projector: nn.Module,
        batch: dict[str, Any],
    ) -> tuple[torch.Tensor, torch.Tensor]:
        frame_mask, real = memory_frames(batch)  # (B, K, S), (n_real, 3, H, W)
        b, k, s = frame_mask.shape
        features = projector.fc1.weight.new_zeros(
            b, k, s, self.num_patches, self.feature_dim
        )  # (B, K, S, P, D_v)
        if real.shape[0]:
            features[frame_mask] = encode_frames(vision_backbone, real).to(features.dtype)
        tokens = self.set_tokens(
            projector,
            features.flatten(0, 1),
            frame_mask.flatten(0, 1),
            batch[MEMORY_BOXES].flatten(0, 1),
            batch[MEMORY_BOX_VISIBLE].bool().flatten(0, 1),
        )  # (B*K, m, D)
        m = tokens.shape[1]
        set_mask = frame_mask.any(dim=-1).repeat_interleave(m, dim=1)  # (B, K*m)
        return tokens.reshape(b, k * m, -1), set_mask

    def new_episode(self) -> KeyframeEpisodeMemory:
        return KeyframeEpisodeMemory(MemoryBank(self.capacity))

    def read(
        self,
        vision_backbone: nn.Module,
        projector: nn.Module,
        episodes: list[EpisodeState],
        frames: StepFrames,
    ) -> list[torch.Tensor]:
        empty = frames.current[0, :0]  # (0, D): the dtype and device of an empty memory
        return [torch.cat([empty, *episode.memory.bank.tokens()], dim=0) for episode in episodes]

    def write(self, projector: nn.Module, episodes: list[EpisodeState], frames: StepFrames) -> None:
        """Keep each frame's features, then push newly completed keyframe sets (same selector as the dataset,
        predicted boxes) into the banks, all episodes' sets in one batch."""
        for row, episode in enumerate(episodes):
            episode.memory.frame_features[episode.step - 1] = frames.patches[row]
        pending = []  # (episode, frames)
        for episode in episodes:
            for frame_set in self.selector.select(episode.actions, episode.box_areas, episode.step):
                if tuple(frame_set) not in episode.memory.bank:
                    pending.append((episode, frame_set))
            episode.memory.forget_features_before(episode.step - self.selector.set_size)
        if not pending:
            return
        size = max(len(frame_set) for _, frame_set in pending)
        first = next(iter(pending[0][0].memory.frame_features.values()))
        features = first.new_zeros(len(pending), size, *first.shape)  # (N, S, P, D_v)
        frame_mask = torch.zeros(len(pending), size, dtype=torch.bool, device=first.device)  # (N, S)
        boxes = torch.zeros(len(pending), size, 4, device=first.device)  # (N, S, 4)
        for row, (episode, frame_set) in enumerate(pending):
            for col, frame in enumerate(frame_set):
                features[row, col] = episode.memory.frame_features[frame]
                boxes[row, col] = torch.tensor(episode.boxes[frame], device=first.device)
            frame_mask[row, : len(frame_set)] = True
        tokens = self.set_tokens(projector, features, frame_mask, boxes, frame_mask)  # (N, m, D)
        for row, (episode, frame_set) in enumerate(pending):
            episode.memory.bank.push(tuple(frame_set), tokens[row])


@KeyframeEncodingConfig.register_builder
def _keyframe_memory(
    encoding: KeyframeEncodingConfig, cfg: ModelConfig, selector: KeyframeSelector
) -> KeyframeMemory:
    return KeyframeMemory(cfg, selector)
