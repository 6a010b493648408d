"""Sequence layout per step: `[BOS] [memory tokens, oldest first] [current frame tokens] [prompt] [action]`.

Masked-out visual slots (missing keyframe sets) and padding take no position: position ids count only the
attended tokens, so a right-padded training row, a left-padded inference row and an unpadded single row give
every real token the same position.
"""

from __future__ import annotations

import torch

from openfly_agent.constants import IGNORE_INDEX


def splice_after_bos(
    text_embeds: torch.Tensor,
    attention_mask: torch.Tensor,
    labels: torch.Tensor | None,
    visual: torch.Tensor,
    visual_mask: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
    """Insert visual tokens after column 0 (BOS) of right-padded text.

    Args:
        text_embeds: (B, L, D) embeddings of `[BOS] prompt action (+EOS) pad...`.
        attention_mask: (B, L).
        labels: (B, L) or None.
        visual: (B, V, D) memory then current-frame tokens.
        visual_mask: (B, V) bool, False for missing memory slots.

    Returns:
        (B, L + V, D) embeddings, (B, L + V) long mask, (B, L + V) labels (visual positions ignored) or None.
    """
    b, v = visual.shape[:2]
    embeds = torch.cat([text_embeds[:, :1], visual.to(text_embeds.dtype), text_embeds[:, 1:]], dim=1)
    mask = torch.cat(
        [attention_mask[:, :1], visual_mask.to(attention_mask.dtype), attention_mask[:, 1:]], dim=1
    )
    if labels is not None:
        ignore = labels.new_full((b, v), IGNORE_INDEX)
        labels = torch.cat([labels[:, :1], ignore, labels[:, 1:]], dim=1)
    return embeds, mask.long(), labels


def position_ids_from_mask(attention_mask: torch.Tensor) -> torch.Tensor:
    """(B, L) mask -> (B, L) positions counting attended tokens only (0 on leading padding)."""
    return (attention_mask.long().cumsum(dim=-1) - 1).clamp(min=0)


def left_pad(sequences: list[torch.Tensor]) -> tuple[torch.Tensor, torch.Tensor]:
    """Stack (L_i, D) sequences left-padded with zeros -> (B, L_max, D) and a (B, L_max) long mask."""
    longest = max(seq.shape[0] for seq in sequences)
    dim = sequences[0].shape[-1]
    ref = sequences[0]
    embeds = ref.new_zeros(len(sequences), longest, dim)
    mask = torch.zeros(len(sequences), longest, dtype=torch.long, device=ref.device)
    for row, seq in enumerate(sequences):
        embeds[row, longest - seq.shape[0] :] = seq
        mask[row, longest - seq.shape[0] :] = 1
    return embeds, mask
