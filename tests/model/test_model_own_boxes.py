"""`model.action_head.box_token_predicted_fraction` (model/agent.py `_token_boxes`): in training, that share of
rows embeds the grounding head's own box, detached, in the box token instead of the jittered true box."""

from __future__ import annotations

import dataclasses

import pytest
import torch

from openfly_agent import constants as C
from openfly_agent.model.language.config import DiscreteActionHeadConfig


def own_box_agent(make_agent, fraction: float):
    """A training-mode agent without box jitter (so the true box is the box itself) and `fraction`."""
    agent = make_agent(action_head=DiscreteActionHeadConfig(box_token_jitter=0.0))
    agent.model_cfg.action_head = dataclasses.replace(
        agent.model_cfg.action_head, box_token_predicted_fraction=fraction
    )
    return agent.train()


def head_boxes(agent, batch) -> tuple[torch.Tensor, torch.Tensor]:
    """The boxes and visibility the grounding head predicts in the training pass itself (fraction 0), read where
    the network's heads return them."""
    network, seen = agent.network, {}
    heads = network.heads

    def recording(*args, **kwargs):
        logits, grounding = heads(*args, **kwargs)
        seen["grounding"] = grounding
        return logits, grounding

    network.heads = recording
    try:
        agent(batch)
    finally:
        del network.heads
    boxes, visible = network.predicted_boxes(seen["grounding"], len(batch[C.BOX]))
    return boxes.detach(), torch.tensor(visible)


def test_every_row_on_its_own_box_is_the_same_as_being_given_that_box(make_agent, make_batch):
    """Fraction 1: the loss, the action logits and every gradient equal those of a batch that hands the head's own
    boxes to the box token (`token_box`), so nothing flows back through the predicted box."""
    agent = own_box_agent(make_agent, 0.0)
    batch = make_batch(agent, batch_size=4)
    boxes, visible = head_boxes(agent, batch)
    assert not torch.allclose(boxes, batch[C.BOX])  # an untrained head: its boxes are not the true ones

    given: dict = {}
    loss_given, _ = agent({**batch, C.TOKEN_BOX: boxes, C.TOKEN_BOX_VISIBLE: visible}, outputs=given)
    loss_given.backward()
    grads_given = {n: p.grad.clone() for n, p in agent.named_parameters() if p.grad is not None}
    agent.zero_grad(set_to_none=True)

    agent.model_cfg.action_head = dataclasses.replace(
        agent.model_cfg.action_head, box_token_predicted_fraction=1.0
    )
    own: dict = {}
    loss_own, _ = agent(batch, outputs=own)
    loss_own.backward()
    torch.testing.assert_close(own["action_logits"], given["action_logits"])
    torch.testing.assert_close(loss_own, loss_given)
    grads_own = {n: p.grad for n, p in agent.named_parameters() if p.grad is not None}
    assert grads_own.keys() == grads_given.keys()
    for name, grad in grads_own.items():
        torch.testing.assert_close(grad, grads_given[name], msg=name)


def test_half_the_rows_take_the_own_box_the_others_the_true_box(make_agent, make_batch):
    agent = own_box_agent(make_agent, 0.0)
    batch = make_batch(agent, batch_size=8)
    boxes, visible = head_boxes(agent, batch)
    logits = {}
    for name, extra in (("true", {}), ("own", {C.TOKEN_BOX: boxes, C.TOKEN_BOX_VISIBLE: visible})):
        out: dict = {}
        agent({**batch, **extra}, outputs=out)
        logits[name] = out["action_logits"].detach()
    agent.model_cfg.action_head = dataclasses.replace(
        agent.model_cfg.action_head, box_token_predicted_fraction=0.5
    )
    kinds = set()
    for seed in range(3):
        torch.manual_seed(seed)
        drawn = torch.rand(8) < 0.5  # the draw `_token_boxes` makes first
        torch.manual_seed(seed)
        out: dict = {}
        agent(batch, outputs=out)
        for row in range(8):
            expected = logits["own" if drawn[row] else "true"][row]
            torch.testing.assert_close(out["action_logits"][row], expected)
            kinds.add(bool(drawn[row]))
    assert kinds == {True, False}


@pytest.mark.parametrize("fraction, training, passes", [(0.0, True, 1), (0.5, False, 1), (0.5, True, 2)])
def test_the_extra_pass_runs_only_in_training_with_a_fraction(
    make_agent, make_batch, fraction, training, passes
):
    agent = own_box_agent(make_agent, fraction).train(training)
    calls = []
    handle = agent.network.register_forward_hook(lambda *args: calls.append(1))
    agent(make_batch(agent, batch_size=2))
    handle.remove()
    assert len(calls) == passes


@pytest.mark.parametrize("fraction", [-0.1, 1.5])
def test_the_fraction_is_a_share(fraction):
    with pytest.raises(ValueError, match="box_token_predicted_fraction"):
        DiscreteActionHeadConfig(box_token_predicted_fraction=fraction)
