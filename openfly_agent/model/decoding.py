"""Decoding after the prefill with the KV cache: one given input embedding (the box token) or greedy tokens
(the OpenVLA bins head), through the agent's decoder stack (`run_llm`)."""

from __future__ import annotations

import torch

from .sequence import position_ids_from_mask


def decode_one(agent, token: torch.Tensor, mask: torch.Tensor, cache) -> tuple[torch.Tensor, torch.Tensor]:
    """Feed one (B, D) input embedding after the prefill (KV cache) -> its (B, 1, D) hidden state and the
    (B, L + 1) mask."""
    positions = position_ids_from_mask(mask)[:, -1:] + 1  # (B, 1)
    mask = torch.cat([mask, mask.new_ones(mask.shape[0], 1)], dim=1)
    out = agent.run_llm(token[:, None], mask, position_ids=positions, past_key_values=cache, use_cache=True)
    return out.last_hidden_state, mask


def greedy_decode(agent, first_logits, mask, cache, steps: int) -> torch.Tensor:
    """Greedy decoding of `steps` tokens reusing the prefill's KV cache (as predict_action, any token).

    Args:
        first_logits: (B, V) logits at the last prefill position.
        mask: (B, L) prefill attention mask.
        cache: the prefill's `past_key_values`.
        steps: tokens to generate.

    Returns:
        (B, steps) token ids.
    """
    token = first_logits.argmax(dim=-1)  # (B,)
    generated = [token]
    positions = position_ids_from_mask(mask)[:, -1:]  # (B, 1)
    for _ in range(steps - 1):
        mask = torch.cat([mask, mask.new_ones(mask.shape[0], 1)], dim=1)
        positions = positions + 1
        out = agent.run_llm(
            agent.embed_text(token[:, None]),
            mask,
            position_ids=positions,
            past_key_values=cache,
            use_cache=True,
        )
        cache = out.past_key_values
        token = agent.lm_logits(out.last_hidden_state[:, -1]).argmax(dim=-1)
        generated.append(token)
    return torch.stack(generated, dim=1)
