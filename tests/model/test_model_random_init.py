"""model/persistence/random_init.py: a meta-built agent materialised with random weights is complete and acts."""

from __future__ import annotations

import numpy as np
import torch

from openfly_agent.model.agent import OpenFlyAgent
from openfly_agent.model.config import make_model_config
from openfly_agent.model.language.tokenizer import train_bpe_tokenizer
from openfly_agent.model.persistence.random_init import INIT_STD, LAYER_SCALE_INIT, materialize_random_


def test_meta_agent_materialised_with_the_documented_values():
    torch.manual_seed(0)
    tokenizer = train_bpe_tokenizer(["fly to the red tower and stop near it"] * 8, vocab_size=300)
    with torch.device("meta"):
        agent = OpenFlyAgent.from_model_config(make_model_config("tiny"), tokenizer=tokenizer)
    materialize_random_(agent, "cpu", torch.float32)
    tensors = dict(agent.named_parameters()) | dict(agent.named_buffers())
    assert not any(t.is_meta for t in tensors.values())
    params = dict(agent.named_parameters())
    matrices = torch.cat([p.detach().flatten() for p in params.values() if p.ndim >= 2])
    assert abs(float(matrices.std()) - INIT_STD) < 2e-3 and abs(float(matrices.mean())) < 1e-3
    gammas = [p for n, p in params.items() if n.endswith("gamma")]
    assert all(torch.all(g == LAYER_SCALE_INIT) for g in gammas)  # the ViT presets' LayerScale
    biases = [p for n, p in params.items() if n.endswith("bias")]
    assert biases and all(torch.all(b == 0) for b in biases)
    rotary = [b for n, b in agent.named_buffers() if "inv_freq" in n]
    assert rotary and all(torch.isfinite(b).all() and (b > 0).all() for b in rotary)
    agent.eval()
    rgb = np.zeros((128, 128, 3), dtype=np.uint8)
    (action,) = agent.new_session().select_action(
        [{"episode_id": "e", "instruction": "fly to the red tower", "rgb": rgb}]
    )
    assert 0 <= action <= 9
