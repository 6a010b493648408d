"""The attention back-ends agree: `llm.attn_implementation` eager and sdpa give the same training forward and the
same cached closed-loop decoding, for the tiny layout and the released (`openvla_compat`) one.

Tolerance: float32 on the CPU, atol 1e-5 and rtol 1e-5 on the loss and the action logits; the bins head's
greedy tokens are equal.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from openfly_agent.model.config import (
    BinsActionHeadConfig,
    HistoryEncodingConfig,
    MemoryConfig,
    PromptConfig,
    TinyLLMConfig,
)
from openfly_agent.model.language.action_tokenizer import CODEBOOK

NORM_STATS = {"demo": {"action": {"q01": [0.0] * 8, "q99": CODEBOOK.max(axis=0).tolist()}}}
INSTRUCTIONS = ["Fly to the red tower and turn left.", "Go straight."]  # two prompt lengths: left padding
VARIANTS = {
    "tiny": {},  # discrete head, box token read after one cached step
    "openvla_compat": {  # history tokens, raw prompt + suffix, 8 bin tokens decoded greedily with the cache
        "memory": MemoryConfig(capacity=2, grid=4, encoding=HistoryEncodingConfig()),
        "prompt": PromptConfig(template="{instruction}", suffix_token_id=5),
        "action_head": BinsActionHeadConfig(decode_rule="nearest"),
    },
}


def llm_section(attn: str) -> TinyLLMConfig:
    """The reduced-width LLM of tests/model/conftest.py's `small_config` with the given back-end."""
    return TinyLLMConfig(
        hidden_size=64, num_layers=2, num_heads=2, intermediate_size=128, attn_implementation=attn
    )


@pytest.fixture
def agent_pair(make_agent, request):
    overrides = VARIANTS[request.param]
    agents = {
        attn: make_agent(seed=1, llm=llm_section(attn), norm_stats=NORM_STATS, **overrides)
        for attn in ("sdpa", "eager")
    }
    agents["eager"].load_state_dict(agents["sdpa"].state_dict())
    with torch.no_grad():  # louder visual tokens: the actions depend on the frames
        for agent in agents.values():
            agent.network.projector.fc3.weight.mul_(10.0)
    for attn, agent in agents.items():
        assert agent.network.causal_lm.config._attn_implementation == attn
    return agents


@pytest.mark.parametrize("agent_pair", list(VARIANTS), indirect=True)
def test_eager_and_sdpa_give_the_same_training_forward(agent_pair, make_batch):
    losses = []
    for agent in agent_pair.values():
        batch = make_batch(agent, batch_size=3)
        torch.manual_seed(0)  # the same box-token jitter
        loss, _ = agent.train()(batch)
        losses.append(loss)
    torch.testing.assert_close(losses[0], losses[1], rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize("agent_pair", list(VARIANTS), indirect=True)
def test_eager_and_sdpa_give_the_same_cached_decoding(agent_pair):
    rng = np.random.default_rng(0)
    frames = rng.integers(0, 256, (2, 3, 56, 56, 3), dtype=np.uint8)  # (episodes, steps, H, W, 3)
    sessions = {attn: agent.eval().new_session() for attn, agent in agent_pair.items()}
    for t in range(3):  # the memory (K = 2) fills up over the steps
        observations = [
            {
                "episode_id": f"ep{e}",
                "instruction": INSTRUCTIONS[e],
                "rgb": frames[e, t],
                "pose": (0, 0, 10, 0),
            }
            for e in range(2)
        ]
        sdpa, eager = (sessions[attn].predict_step(observations) for attn in ("sdpa", "eager"))
        for a, b in zip(sdpa, eager):
            assert a.action == b.action
            if a.action_logits.is_floating_point():  # discrete head: the 10 action logits
                torch.testing.assert_close(a.action_logits, b.action_logits, rtol=1e-5, atol=1e-5)
            else:  # bins head: the 8 greedy tokens
                assert torch.equal(a.action_logits, b.action_logits)
            assert a.box == pytest.approx(b.box, abs=1e-5)


def test_attention_implementation_is_checked():
    with pytest.raises(ValueError, match="attn_implementation='flash'"):
        TinyLLMConfig(attn_implementation="flash")
    assert TinyLLMConfig().attn_implementation == "sdpa"  # today's default
