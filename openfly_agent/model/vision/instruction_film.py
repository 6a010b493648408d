"""Instruction-conditioned vision (`vision.cnn_instruction_film`, tiny-cnn only).

The frame's tokens precede the prompt in the LLM, so without this the cell features never see the text: only
the LLM's later positions and the grounding head's FiLM bind them to the instruction. Here the mean of the
prompt's token embeddings (the LLM's input embedding table; BOS, padding and action targets excluded) is
mapped by an MLP to a per-channel scale and shift of the feature maps entering the ResNet's third and fourth
stages (FiLM, as the channel modulation of the issue's outside prototype): those stages compute features for
the landmark asked for. The last layer starts at zero, so a fresh module is the identity and a checkpoint
trained without it starts where it was.
"""

from __future__ import annotations

import torch
from torch import nn


def mean_prompt_embedding(embeds: torch.Tensor, prompt_mask: torch.Tensor) -> torch.Tensor:
    """(B, L, D) token embeddings, (B, L) bool prompt positions -> (B, D) mean over each row's prompt."""
    weights = prompt_mask.to(embeds.dtype)[..., None]  # (B, L, 1)
    return (embeds * weights).sum(dim=1) / weights.sum(dim=1).clamp(min=1.0)


class InstructionFiLM(nn.Module):
    """(B, D_text) instruction code -> one (scale, shift) pair per modulated stage input.

    Args:
        text_dim: width of the instruction code (the LLM's embedding width).
        widths: channels of each modulated feature map, in the order they are modulated.
    """

    def __init__(self, text_dim: int, widths: tuple[int, ...]) -> None:
        super().__init__()
        self.widths = tuple(widths)
        self.net = nn.Sequential(
            nn.Linear(text_dim, text_dim), nn.GELU(), nn.Linear(text_dim, 2 * sum(self.widths))
        )

    def reset_to_identity(self) -> None:
        """Zero the last layer: every scale 1, every shift 0."""
        nn.init.zeros_(self.net[-1].weight)
        nn.init.zeros_(self.net[-1].bias)

    def forward(self, code: torch.Tensor) -> list[tuple[torch.Tensor, torch.Tensor]]:
        """(B, D_text) -> [(scale (B, C_i, 1, 1), shift (B, C_i, 1, 1))] for each width C_i; apply as
        `x * scale + shift`."""
        params = self.net(code)[..., None, None]  # (B, 2 * sum(C), 1, 1)
        pairs, start = [], 0
        for width in self.widths:
            gamma, beta = params[:, start : start + width], params[:, start + width : start + 2 * width]
            pairs.append((1.0 + gamma, beta))
            start += 2 * width
        return pairs
