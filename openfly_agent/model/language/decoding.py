"""Decoding with a KV cache: the prefill, then one given input embedding (the box token) or greedy tokens
(the OpenVLA bins head), through the agent's decoder stack (`run_llm`).

The cache is a transformers `DynamicCache` made here and filled in place by every call, passed under the
decoder's own keyword (`cache`; `past_key_values` before transformers renamed it), so no deprecated name is
used and the output's cache attribute is never read.
"""

from __future__ import annotations

import functools
import inspect
from typing import Any

import torch

from openfly_agent.model.language.llm import unwrap_causal_lm
from openfly_agent.model.language.sequence import position_ids_from_mask


def new_cache(agent) -> Any:
    """An empty `DynamicCache` for the agent's LLM."""
    from transformers import DynamicCache

    return DynamicCache(config=unwrap_causal_lm(agent.language_model).config)


def run_cached(agent, embeds: torch.Tensor, mask: torch.Tensor, cache, **kwargs) -> Any:
    """`agent.run_llm` over (B, T, D) `embeds` that reads and extends `cache` (in place)."""
    keyword = _cache_keyword(type(unwrap_causal_lm(agent.language_model).model))
    return agent.run_llm(embeds, mask, use_cache=True, **{keyword: cache}, **kwargs)


@functools.cache
def _cache_keyword(decoder_class: type) -> str:
    """The decoder's keyword for the cache (read once per class: every decoding step passes it)."""
    return "cache" if "cache" in inspect.signature(decoder_class.forward).parameters else "past_key_values"


def decode_one(agent, token: torch.Tensor, mask: torch.Tensor, cache) -> tuple[torch.Tensor, torch.Tensor]:
    """Feed one (B, D) input embedding after the prefill (its `cache`) -> its (B, 1, D) hidden state and the
    (B, L + 1) mask."""
    positions = position_ids_from_mask(mask)[:, -1:] + 1  # (B, 1)
    mask = torch.cat([mask, mask.new_ones(mask.shape[0], 1)], dim=1)
    out = run_cached(agent, token[:, None], mask, cache, position_ids=positions)
    return out.last_hidden_state, mask


def greedy_decode(agent, first_logits, mask, cache, steps: int) -> torch.Tensor:
    """Greedy decoding of `steps` tokens reusing the prefill's KV cache (as predict_action, any token).

    Args:
        first_logits: (B, V) logits at the last prefill position.
        mask: (B, L) prefill attention mask.
        cache: the prefill's cache (`new_cache`, filled by `run_cached`).
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
        out = run_cached(agent, agent.embed_text(token[:, None]), mask, cache, position_ids=positions)
        token = agent.lm_logits(out.last_hidden_state[:, -1]).argmax(dim=-1)
        generated.append(token)
    return torch.stack(generated, dim=1)
