"""`OpenFlyNetwork` (model/network.py): cached decoding, the agent's modules shared under their old keys."""

from __future__ import annotations

import torch

from openfly_agent.model.config import BinsActionHeadConfig
from openfly_agent.model.language.action_tokenizer import CODEBOOK
from openfly_agent.model.language.sequence import left_pad

NORM_STATS = {"demo": {"action": {"q01": [0.0] * 8, "q99": CODEBOOK.max(axis=0).tolist()}}}


def test_kv_cache_decoding_equals_full_recompute(make_agent):
    network = make_agent(action_head=BinsActionHeadConfig(), norm_stats=NORM_STATS).network
    torch.manual_seed(1)
    rows = [torch.randn(n, network.llm_dim) for n in (7, 4, 9)]
    embeds, mask = left_pad(rows)
    cache = network.new_cache()
    out = network.run_cached(embeds, mask, cache)
    cached = network.greedy_decode(network.lm_logits(out.last_hidden_state[:, -1]), mask, cache, 8)
    seq, seq_mask, tokens = embeds, mask, []
    for _ in range(8):
        token = network.lm_logits(network.run_llm(seq, seq_mask).last_hidden_state[:, -1]).argmax(-1)
        tokens.append(token)
        seq = torch.cat([seq, network.embed_text(token[:, None])], dim=1)
        seq_mask = torch.cat([seq_mask, seq_mask.new_ones(3, 1)], dim=1)
    assert torch.equal(cached, torch.stack(tokens, dim=1))


def test_the_agent_keeps_the_state_dict_keys_of_its_modules(make_agent):
    """The network is not a child of the agent: the keys stay `vision_backbone.*`, ..., the network's own."""
    agent = make_agent()
    keys = list(agent.state_dict())
    assert keys == list(agent.network.state_dict())
    assert {key.split(".", 1)[0] for key in keys} == {
        "vision_backbone",
        "projector",
        "language_model",
        "grounding_head",
        "box_token_embed",
    }
    replaced = torch.nn.Linear(2, 2)
    agent.projector = replaced  # a module replaced on the agent (as LoRA's wrapper) is the network's too
    assert agent.network.projector is replaced
