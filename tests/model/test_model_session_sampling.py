"""`AgentSession(temperature=..., generator=...)` (model/session.py): sampled actions for the RL stage's rollouts.

Temperature 0 keeps greedy decoding; above it the actions follow softmax(action logits / temperature), drawn from
the given generator, so the same seed gives the same flights."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from openfly_agent.model.config import BinsActionHeadConfig
from openfly_agent.model.language.action_tokenizer import CODEBOOK
from openfly_agent.model.session import AgentSession

ROWS = 400  # one frame seen by this many episodes at once: the same logits, independent draws


def _observations(rows: int = ROWS) -> list[dict]:
    frame = np.random.default_rng(3).integers(0, 256, (56, 56, 3), dtype=np.uint8)
    return [
        {"episode_id": f"ep{i}", "instruction": "fly to the red tower", "rgb": frame, "pose": (0, 0, 10, 0)}
        for i in range(rows)
    ]


def _agent(make_agent):
    agent = make_agent(seed=1)
    with (
        torch.no_grad()
    ):  # logits a few units apart (a fresh init's are all about 0): a policy worth sampling
        agent.network.language_model.lm_head.weight.mul_(10.0)
    return agent


def test_greedy_by_default_and_at_temperature_zero(make_agent):
    agent = _agent(make_agent)
    results = AgentSession(agent).predict_step(_observations(4))
    greedy = int(results[0].action_logits.argmax())
    assert [r.action for r in results] == [greedy] * 4
    zero = AgentSession(agent, temperature=0.0, generator=torch.Generator().manual_seed(0))
    assert [r.action for r in zero.predict_step(_observations(4))] == [greedy] * 4


def test_sampled_actions_follow_the_tempered_softmax(make_agent):
    agent = _agent(make_agent)
    session = AgentSession(agent, temperature=2.0, generator=torch.Generator().manual_seed(0))
    results = session.predict_step(_observations())
    probs = torch.softmax(results[0].action_logits.float() / 2.0, dim=-1).numpy()  # (10,)
    assert probs.max() < 0.9, "the test needs a policy that is not (almost) deterministic"
    counts = np.bincount([r.action for r in results], minlength=10) / ROWS
    # 400 draws: each frequency within 4 standard errors sqrt(p (1 - p) / 400) <= 0.1 of its probability
    assert np.all(np.abs(counts - probs) <= 4 * np.sqrt(probs * (1 - probs) / ROWS) + 1e-9), (counts, probs)
    assert len({r.action for r in results}) > 1


def test_the_same_seed_gives_the_same_samples(make_agent):
    agent = _agent(make_agent)

    def draw(seed: int) -> list[int]:
        session = AgentSession(agent, temperature=1.0, generator=torch.Generator().manual_seed(seed))
        return [r.action for r in session.predict_step(_observations(64))]

    assert draw(5) == draw(5)
    assert draw(5) != draw(6)


def test_sampling_needs_the_discrete_head_and_a_non_negative_temperature(make_agent):
    norm_stats = {"demo": {"action": {"q01": [0.0] * 8, "q99": CODEBOOK.max(axis=0).tolist()}}}
    bins = make_agent(action_head=BinsActionHeadConfig(unnorm_key="demo"), norm_stats=norm_stats)
    with pytest.raises(ValueError, match="discrete"):
        AgentSession(bins, temperature=1.0)
    with pytest.raises(ValueError, match=">= 0"):
        AgentSession(make_agent(), temperature=-1.0)
