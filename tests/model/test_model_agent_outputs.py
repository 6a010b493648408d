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
    assert float(outputs["grounding_loss"].detach()) == logs["grounding_loss"]
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
