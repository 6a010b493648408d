"""The box token: the target's box as one input embedding after the prompt, where the action is read.

With `action_head.box_token` the step's sequence is `[BOS] [memory] [current] [prompt] [BOX] -> action`: the
LLM reads the action at the BOX position, whose input embedding encodes where the instruction's target is in the
frame. At inference BOX carries the grounding head's prediction from the prefill of `[BOS] .. [prompt]` (then one
cached decode step); in training the ground-truth box, jittered so the action learns to tolerate a grounding
head's errors. The grounding head never reads the BOX position, so both see the same prefix.
"""

from __future__ import annotations

import torch
from torch import nn

from openfly_agent.constants import IGNORE_INDEX

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


def insert_before_targets(
    embeds: torch.Tensor, mask: torch.Tensor, labels: torch.Tensor, token: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Insert `token` right before each row's first labelled position (right-padded training rows).

    Args:
        embeds: (B, L, D) input embeddings; mask: (B, L); labels: (B, L) with IGNORE_INDEX off the targets.
        token: (B, D) the embedding to insert.

    Returns:
        (B, L + 1, D) embeddings, (B, L + 1) mask, (B, L + 1) labels (IGNORE_INDEX at the token) and the
        (B,) positions of the inserted tokens. The target predicted at the token is the first label after it.
    """
    b, length = labels.shape
    labelled = labels != IGNORE_INDEX  # (B, L)
    if not bool(labelled.any(dim=1).all()):
        raise ValueError("every row needs a labelled action token to put the box token before")
    position = labelled.long().argmax(dim=1)  # (B,) first labelled column
    columns = torch.arange(length + 1, device=labels.device)[None]  # (1, L + 1)
    source = columns - (columns > position[:, None]).long()  # (B, L + 1) old column of each new column
    source = source.clamp(max=length - 1)
    rows = torch.arange(b, device=labels.device)[:, None]
    at_token = columns == position[:, None]  # (B, L + 1)
    new_embeds = torch.where(at_token[..., None], token[:, None].to(embeds.dtype), embeds[rows, source])
    new_mask = torch.where(at_token, torch.ones_like(mask[:, :1]), mask[rows, source])
    new_labels = torch.where(at_token, torch.full_like(labels[:, :1], IGNORE_INDEX), labels[rows, source])
    return new_embeds, new_mask, new_labels, position


def last_true_index(mask: torch.Tensor) -> torch.Tensor:
    """(B, L) bool -> (B,) index of each row's last True column (0 for an all-False row)."""
    columns = torch.arange(mask.shape[1], device=mask.device)[None]
    return (mask.long() * columns).amax(dim=1)
