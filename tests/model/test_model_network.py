"""`OpenFlyNetwork` (model/network.py): cached decoding, a child module of the agent whose saved names stay
`vision_backbone.*`, ..., and its entry points called by training and inference alike."""

from __future__ import annotations

import numpy as np
import torch
from safetensors.torch import load_file

from openfly_agent.model.config import BinsActionHeadConfig
from openfly_agent.model.language.action_tokenizer import CODEBOOK
from openfly_agent.model.layout import SequenceLayout

NORM_STATS = {"demo": {"action": {"q01": [0.0] * 8, "q99": CODEBOOK.max(axis=0).tolist()}}}
SAVED_PARTS = {"vision_backbone", "projector", "language_model", "grounding_head", "box_token_embed"}


def test_kv_cache_decoding_equals_full_recompute(make_agent):
    agent = make_agent(action_head=BinsActionHeadConfig(), norm_stats=NORM_STATS)
    network = agent.network
    torch.manual_seed(1)
    rows = [torch.randn(n, network.llm_dim) for n in (7, 4, 9)]
    no_memory = [row[:0] for row in rows]
    layout = SequenceLayout.for_inference(rows, no_memory, torch.zeros(3, 0, network.llm_dim))
    cache = network.new_cache()
    logits, _ = network.heads(network(layout, cache), layout, boxes=False)
    cached = network.decode_actions(logits, layout, cache, agent.action_tokenizer)  # (3, 8)
    seq, seq_mask, tokens = layout.embeds, layout.mask, []
    for _ in range(8):
        token = network.lm_logits(network.run_llm(seq, seq_mask).last_hidden_state[:, -1]).argmax(-1)
        tokens.append(token)
        seq = torch.cat([seq, network.embed_text(token[:, None])], dim=1)
        seq_mask = torch.cat([seq_mask, seq_mask.new_ones(3, 1)], dim=1)
    assert torch.equal(cached, torch.stack(tokens, dim=1))


def test_the_network_is_a_child_module_saved_under_the_openvla_names(make_agent, tmp_path):
    agent = make_agent()
    assert dict(agent.named_children())["network"] is agent.network
    assert {key.split(".", 2)[1] for key in agent.state_dict()} == SAVED_PARTS  # network.<part>.*
    agent.save_pretrained(tmp_path)
    saved = load_file(str(tmp_path / "model.safetensors"))
    assert {key.split(".", 1)[0] for key in saved} == SAVED_PARTS  # no `network.` on disk
    assert saved.keys() == agent.network.state_dict().keys()
    agent.train()
    assert agent.network.training and agent.network.grounding_head.training  # no override keeps them in step
    agent.eval()
    assert not agent.network.training


def test_the_agent_loads_a_state_dict_under_the_saved_names(make_agent):
    """Resume files written while the network shared the agent's modules hold `projector.*`, ...: they load."""
    source, target = make_agent(seed=0), make_agent(seed=1)
    result = target.load_state_dict(source.network.state_dict(), strict=True)
    assert not result.missing_keys and not result.unexpected_keys
    assert torch.equal(target.network.projector.fc1.weight, source.network.projector.fc1.weight)


def test_a_forward_hook_on_the_network_fires_in_training_and_inference(make_agent, make_batch):
    agent = make_agent()
    fired = []  # (training flag, hidden states' shape) per call of the network
    agent.network.register_forward_hook(lambda module, args, out: fired.append((module.training, out.shape)))
    agent.train()
    batch = make_batch(agent, batch_size=2)
    agent(batch)
    assert [training for training, _ in fired] == [True]
    # [BOS] [2 memory sets of 2 x 2 tokens] [16 frame tokens] [prompt] [BOX] [action]: the text, 8, 16 and 1
    assert fired[0][1][:2] == (2, batch["input_ids"].shape[1] + 8 + 16 + 1)
    fired.clear()
    agent.eval()
    size = agent.model_cfg.vision.image_size
    observation = {
        "episode_id": "e0",
        "instruction": "fly to the red tower",
        "rgb": np.zeros((size, size, 3), np.uint8),
        "pose": [0.0, 0.0, 0.0, 0.0],
    }
    session = agent.new_session()
    session.predict_step([observation])
    prefill = len(session.episodes["e0"].prompt_ids) + 16  # [BOS] [16 frame tokens] [prompt]: no memory yet
    assert [(training, shape[1]) for training, shape in fired] == [(False, prefill), (False, 1)]  # then BOX
