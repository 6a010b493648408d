"""The box token: the target's box as one input embedding after the prompt, where the action is read.

With `action_head.box_token` the step's sequence is `[BOS] [memory] [current] [prompt] [BOX] -> action`: the
LLM reads the action at the BOX position, whose input embedding encodes where the instruction's target is in the
frame. At inference BOX carries the grounding head's prediction from the prefill of `[BOS] .. [prompt]` (then one
cached decode step); in training the ground-truth box, jittered so the action learns to tolerate a grounding
head's errors. The grounding head never reads the BOX position, so both see the same prefix. Where BOX goes is
the sequence layout's (model/layout.py); this module makes its embedding.
"""

from __future__ import annotations

import torch
from torch import nn

NUM_BOX_FEATURES = 6  # visible, cx - 0.5, cy - 0.5, sqrt(area), w, h


def box_features(boxes: torch.Tensor, visible: torch.Tensor) -> torch.Tensor:
    """(B, 4) cxcywh in [0, 1] and (B,) bool -> (B, 6) features; all zeros for an invisible target."""
    cx, cy, w, h = boxes.float().unbind(-1)
    features = torch.stack(
        [torch.ones_like(cx), cx - 0.5, cy - 0.5, (w * h).clamp(min=0).sqrt(), w, h], dim=-1
    )
    return features * visible.to(features.dtype)[:, None]


def given_boxes(boxes: list, device=None) -> tuple[torch.Tensor, list[bool]]:
    """A list of (cx, cy, w, h) or None (not visible) -> (B, 4) float boxes (zeros where None), (B,) visibility."""
    rows = [[0.0] * 4 if box is None else [float(v) for v in box] for box in boxes]
    if any(len(row) != 4 for row in rows):
        raise ValueError(f"boxes must be (cx, cy, w, h) or None, got {boxes}")
    return torch.tensor(rows, dtype=torch.float32, device=device), [box is not None for box in boxes]


def jitter_boxes(boxes: torch.Tensor, std: float) -> torch.Tensor:
    """Training noise on (B, 4) cxcywh: the centre moves by N(0, std), width and height scale by exp(N(0, 2 std))."""
    if std <= 0:
        return boxes
    centre = boxes[:, :2] + torch.randn_like(boxes[:, :2]) * std
    size = boxes[:, 2:] * torch.exp(torch.randn_like(boxes[:, 2:]) * 2 * std)
    return torch.cat([centre, size], dim=-1).clamp(0.0, 1.0)


class BoxTokenEmbedding(nn.Module):
    """(B, 6) box features -> (B, D) an input embedding of the LLM (a 2-layer GELU MLP)."""

    def __init__(self, llm_dim: int) -> None:
        super().__init__()
        self.fc1 = nn.Linear(NUM_BOX_FEATURES, llm_dim)
        self.fc2 = nn.Linear(llm_dim, llm_dim)

    def forward(self, boxes: torch.Tensor, visible: torch.Tensor) -> torch.Tensor:
        features = box_features(boxes, visible).to(self.fc1.weight.dtype)
        return self.fc2(nn.functional.gelu(self.fc1(features)))
