"""Frames and keyframe memory -> features and LLM tokens: frames through the vision backbone, each keyframe set
merged into its largest-box frame, grid-pooled and projected (openfly mode), or one token per history frame (openvla_compat).

`MemoryEncoding` is a mixin of `OpenFlyAgent` (model/agent.py): it uses the agent's `vision_backbone`,
`projector`, `embed_text` and `model_cfg`.
"""

from __future__ import annotations

from typing import Any

import torch

from openfly_agent.constants import (
    MEMORY_BOX_VISIBLE,
    MEMORY_BOXES,
    MEMORY_FRAME_MASK,
    MEMORY_PIXEL_VALUES,
    PIXEL_VALUES,
)
from openfly_agent.model.config import MODE_OPENVLA_COMPAT
from openfly_agent.model.memory.bank import grid_pool
from openfly_agent.model.memory.merging import choose_reference, merge_into_reference


class MemoryEncoding:
    """Frame features, and the memory tokens of a training batch and of the agent's online keyframe sets."""

    def encode_frames(self, pixels: torch.Tensor, frame_index: torch.Tensor | None = None) -> torch.Tensor:
        """(F, 3, H, W) uint8 -> (N, P, D_v) features; sequence i reads frame `frame_index[i]` (default i)."""
        features = self.vision_backbone(pixels)  # (F, P, D_v)
        return features if frame_index is None else features[frame_index.to(features.device)]

    def memory_set_tokens(
        self, features: torch.Tensor, frame_mask: torch.Tensor, boxes: torch.Tensor, box_visible: torch.Tensor
    ) -> torch.Tensor:
        """Keyframe sets -> memory tokens: merge into the largest-box frame, grid-pool, project.

        Args:
            features: (N, S, P, D_v) fused features of each frame of each set.
            frame_mask: (N, S) bool, real frames.
            boxes: (N, S, 4) landmark boxes (ground truth in training, predicted online).
            box_visible: (N, S) bool.

        Returns:
            (N, (sqrt(P) / g)^2, D_llm) tokens.
        """
        reference = choose_reference(boxes.to(features.device), box_visible.to(features.device), frame_mask)
        merging = self.model_cfg.merging
        if merging.enabled:
            merged = merge_into_reference(features, frame_mask, reference, merging.threshold, merging.top_r)
        else:
            merged = features[
                torch.arange(features.shape[0], device=features.device), reference
            ]  # (N, P, D_v)
        return self.projector(grid_pool(merged, self.model_cfg.memory.grid))  # (N, m, D)

    def history_tokens(self, patches: torch.Tensor, dino_cls: torch.Tensor) -> torch.Tensor:
        """openvla_compat: one token per history frame = DINO CLS ++ pooled SigLIP patches -> (N, D_llm)."""
        siglip = patches[..., self.vision_backbone.dino_dim :]  # (N, P, D_siglip)
        pooled = grid_pool(siglip, self.model_cfg.memory.grid)[:, 0]  # (N, D_siglip)
        return self.projector(torch.cat([dino_cls, pooled], dim=-1))  # (N, D)

    def encode_memory_batch(self, batch: dict[str, Any]) -> tuple[torch.Tensor, torch.Tensor]:
        """Memory tokens of a training batch -> (B, M, D) tokens and (B, M) bool mask (missing sets off)."""
        current = batch[PIXEL_VALUES]
        b = current.shape[0]
        if self.model_cfg.memory.capacity == 0 or MEMORY_PIXEL_VALUES not in batch:
            empty = torch.zeros(
                b, 0, self.llm_dim, device=current.device, dtype=self.projector.fc1.weight.dtype
            )
            return empty, torch.zeros(b, 0, dtype=torch.bool, device=current.device)
        pixels = batch[MEMORY_PIXEL_VALUES]  # (B, K, S, 3, H, W)
        frame_mask = batch[MEMORY_FRAME_MASK].bool().to(pixels.device)  # (B, K, S)
        _, k, s = pixels.shape[:3]
        if k > self.model_cfg.memory.capacity:
            raise ValueError(
                f"batch holds {k} memory sets but memory.capacity is {self.model_cfg.memory.capacity}"
            )
        real = pixels[frame_mask]  # (n_real, 3, H, W)
        if self.model_cfg.mode == MODE_OPENVLA_COMPAT:
            tokens = self.projector.fc3.weight.new_zeros(b, k * s, self.llm_dim)  # (B, K*S, D)
            if real.shape[0]:
                tokens[frame_mask.view(b, k * s)] = self.history_tokens(
                    *self.vision_backbone.forward_with_cls(real)
                )
            return tokens, frame_mask.view(b, k * s)
        p, dv = self.model_cfg.vision.num_patches, self.model_cfg.vision.feature_dim
        features = self.projector.fc1.weight.new_zeros(b, k, s, p, dv)  # (B, K, S, P, D_v)
        if real.shape[0]:
            features[frame_mask] = self.encode_frames(real).to(features.dtype)
        tokens = self.memory_set_tokens(
            features.flatten(0, 1),
            frame_mask.flatten(0, 1),
            batch[MEMORY_BOXES].flatten(0, 1),
            batch[MEMORY_BOX_VISIBLE].bool().flatten(0, 1),
        )  # (B*K, m, D)
        m = tokens.shape[1]
        set_mask = frame_mask.any(dim=-1).repeat_interleave(m, dim=1)  # (B, K*m)
        return tokens.reshape(b, k * m, -1), set_mask
