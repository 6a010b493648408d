"""`OpenFlyAgent.forward(batch, outputs)` (model/agent.py): the tensors behind the loss for the RL stage, and a
box token fed another box than the grounding target (`token_box`)."""

from __future__ import annotations

import torch
import torch.nn.functional as F

from openfly_agent import constants as C


def test_outputs_hold_the_logits_behind_the_action_loss_and_the_grounding_loss(make_agent, make_batch):
    agent = make_agent()
    batch = make_batch(agent, batch_size=3)
    outputs: dict = {}
    loss, logs = agent(batch, outputs=outputs)
    logits, targets = outputs["action_logits"], outputs["action_targets"]
    assert logits.shape == (3, agent.model_cfg.llm.vocab_size) and targets.shape == (3,)  # one token per step
    assert torch.allclose(F.cross_entropy(logits, targets), torch.tensor(logs["action_loss"]), atol=1e-5)
    assert float(outputs["grounding_loss"]) == logs["grounding_loss"]
    assert torch.allclose(loss, F.cross_entropy(logits, targets) + outputs["grounding_loss"], atol=1e-5)
    plain_loss, _ = agent(batch)  # without outputs: the same loss
    assert torch.equal(plain_loss, loss)


def test_token_box_feeds_the_box_token_and_box_stays_the_grounding_target(make_agent, make_batch):
    agent = make_agent()  # eval mode: no jitter
    batch = make_batch(agent, batch_size=3)
    base: dict = {}
    agent(batch, outputs=base)
    same: dict = {}
    agent({**batch, C.TOKEN_BOX: batch[C.BOX], C.TOKEN_BOX_VISIBLE: batch[C.BOX_VISIBLE]}, outputs=same)
    assert torch.equal(same["action_logits"], base["action_logits"])
    other: dict = {}
    moved = {C.TOKEN_BOX: torch.full((3, 4), 0.1), C.TOKEN_BOX_VISIBLE: torch.ones(3, dtype=torch.bool)}
    agent({**batch, **moved}, outputs=other)
    assert not torch.allclose(other["action_logits"], base["action_logits"])
    # the grounding head reads the positions before the box token: its loss does not change
    assert torch.allclose(other["grounding_loss"], base["grounding_loss"])


def test_the_leg_goal_head_adds_its_weighted_squared_error_and_learns_from_it(make_agent, make_batch):
    """`action_head.leg_goal_weight`: a linear head on the hidden state each action is read from; by hand, its
    loss is the squared error summed over (sin, cos, distance) and averaged over the rows."""
    from openfly_agent.model.config import DiscreteActionHeadConfig

    plain = make_agent(seed=3)
    agent = make_agent(seed=3, action_head=DiscreteActionHeadConfig(leg_goal_weight=0.5))
    assert plain.network.leg_goal_head is None and agent.network.leg_goal_head is not None
    batch = make_batch(agent, batch_size=3)
    target = torch.tensor([[1.0, 0.0, 0.5], [0.0, 1.0, 0.1], [0.0, -1.0, 2.0]])
    outputs: dict = {}
    loss, logs = agent({**batch, C.LEG_GOAL: target}, outputs=outputs)
    base_loss, base_logs = agent(batch)  # no target in the batch: no leg-goal loss
    assert "leg_goal_loss" not in base_logs
    hidden: list = []
    hook = agent.network.leg_goal_head.register_forward_hook(lambda m, args, out: hidden.append(args[0]))
    agent({**batch, C.LEG_GOAL: target})
    hook.remove()
    predicted = agent.network.leg_goal_head(hidden[0])  # (3, 3)
    by_hand = ((predicted - target) ** 2).sum(dim=1).mean()
    assert torch.allclose(torch.tensor(logs["leg_goal_loss"]), by_hand, atol=1e-6)
    assert torch.allclose(loss, base_loss + 0.5 * by_hand, atol=1e-5)
    agent.train()
    loss, _ = agent({**batch, C.LEG_GOAL: target})
    loss.backward()
    assert agent.network.leg_goal_head.weight.grad.abs().sum() > 0


def test_a_negative_leg_goal_weight_is_refused():
    import pytest

    from openfly_agent.model.config import DiscreteActionHeadConfig

    with pytest.raises(ValueError, match="leg_goal_weight"):
        DiscreteActionHeadConfig(leg_goal_weight=-1.0)
