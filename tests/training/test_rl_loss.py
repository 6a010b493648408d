"""The RL stage's objective (training/rl_loss.py) on small tensors, against numbers worked out by hand."""

from __future__ import annotations

import math

import pytest
import torch

from openfly_agent.training.rl_loss import (
    action_log_probs,
    clipped_policy_loss,
    group_advantages,
    k3_kl,
    rl_loss,
)


def test_advantages_are_group_relative_with_the_bessel_corrected_std():
    # group 1: mean 0.5, std sqrt((4 x 0.25) / 3) = 0.57735, so +-0.5 / 0.57735 = +-0.866025 (eps 0)
    # group 2: [2, 0, 0, 0]: mean 0.5, std sqrt((2.25 + 3 x 0.25) / 3) = 1, so [1.5, -0.5, -0.5, -0.5]
    rewards = torch.tensor([[1.0, 0.0, 0.0, 1.0], [2.0, 0.0, 0.0, 0.0]])
    advantages = group_advantages(rewards, eps=1e-12)
    expected = torch.tensor([[0.866025, -0.866025, -0.866025, 0.866025], [1.5, -0.5, -0.5, -0.5]])
    assert torch.allclose(advantages, expected, atol=1e-5)


def test_a_group_with_equal_rewards_gets_zero_advantages():
    advantages = group_advantages(torch.tensor([[1.0, 1.0, 1.0], [0.0, 0.0, 0.0], [0.0, 1.0, 0.0]]), eps=1e-4)
    assert advantages[:2].abs().sum() == 0
    assert advantages[2].abs().sum() > 0


def test_advantages_need_groups_of_two():
    with pytest.raises(ValueError, match="G >= 2"):
        group_advantages(torch.tensor([[1.0], [0.0]]), eps=1e-4)


def test_clipped_loss_by_hand():
    # ratios e^{ln 1.5} = 1.5, e^{ln 0.5} = 0.5, 1.1, 1.5; eps 0.2
    logp = torch.log(torch.tensor([1.5, 0.5, 1.1, 1.5]))
    old = torch.zeros(4)
    adv = torch.tensor([1.0, -1.0, 2.0, -1.0])
    loss, clipped = clipped_policy_loss(logp, old, adv, clip_epsilon=0.2)
    # A = 1, r = 1.5: min(1.5, 1.2) = 1.2 (clipped); A = -1, r = 0.5: min(-0.5, -0.8) = -0.8 (clipped);
    # A = 2, r = 1.1: inside the clip, 2.2; A = -1, r = 1.5: min(-1.5, -1.2) = -1.5 (unclipped: pessimistic)
    assert torch.allclose(loss, torch.tensor([-1.2, 0.8, -2.2, 1.5]), atol=1e-6)
    assert clipped.tolist() == [True, True, False, False]


def test_clipped_tokens_carry_no_gradient():
    logp = torch.log(torch.tensor([1.5, 1.1])).requires_grad_(True)
    loss, _ = clipped_policy_loss(logp, torch.zeros(2), torch.tensor([1.0, 1.0]), clip_epsilon=0.2)
    loss.sum().backward()
    # d(-r A)/d logp = -r A = -1.1 inside the clip; 0 where the clipped term is taken
    assert torch.allclose(logp.grad, torch.tensor([0.0, -1.1]), atol=1e-6)


def test_k3_kl_by_hand():
    # ref - logp = d: exp(d) - d - 1; d = 0 -> 0; d = ln 2 -> 2 - 0.693147 - 1 = 0.306853; d = -ln 2 -> 0.5 + 0.693147 - 1
    logp = torch.tensor([-1.0, -1.0, -1.0])
    ref = torch.tensor([-1.0, -1.0 + math.log(2), -1.0 - math.log(2)])
    assert torch.allclose(k3_kl(logp, ref), torch.tensor([0.0, 0.306853, 0.193147]), atol=1e-6)


def test_zero_advantages_and_the_reference_policy_give_zero_loss():
    logp = torch.tensor([-0.3, -2.0, -1.1], requires_grad=True)
    total, parts = rl_loss(logp, logp.detach(), logp.detach(), torch.zeros(3), clip_epsilon=0.2, kl_coef=0.1)
    assert float(total.detach()) == 0.0 and float(parts["kl"]) == 0.0 and float(parts["clipped"]) == 0.0
    total.backward()
    assert logp.grad.abs().sum() == 0


def test_rl_loss_sums_policy_and_kl_terms():
    logp = torch.log(torch.tensor([1.5, 1.1]))
    ref = logp + torch.tensor([math.log(2), 0.0])
    total, parts = rl_loss(logp, torch.zeros(2), ref, torch.tensor([1.0, 2.0]), clip_epsilon=0.2, kl_coef=0.5)
    # policy: -1.2 - 2.2 = -3.4; kl: 0.306853 + 0; total -3.4 + 0.5 x 0.306853
    assert math.isclose(float(parts["pg_loss"]), -3.4, abs_tol=1e-5)
    assert math.isclose(float(total), -3.4 + 0.5 * 0.306853, abs_tol=1e-5)


def test_action_log_probs_read_the_action_tokens_at_the_temperature():
    # vocabulary of 6, actions are tokens 3, 4, 5; logits of those: [0, ln 2, ln 5] -> at T = 1: [1, 2, 5] / 8
    logits = torch.tensor([[9.0, 9.0, 9.0, 0.0, math.log(2), math.log(5)]] * 2)
    ids = torch.tensor([3, 4, 5])
    logp, entropy = action_log_probs(logits, torch.tensor([4, 5]), ids, temperature=1.0)
    assert torch.allclose(logp, torch.log(torch.tensor([2 / 8, 5 / 8])), atol=1e-6)
    p = torch.tensor([1 / 8, 2 / 8, 5 / 8])
    assert torch.allclose(entropy, -(p * p.log()).sum().expand(2), atol=1e-6)
    # T = 2 halves the logits: probabilities prop. to sqrt([1, 2, 5])
    logp2, _ = action_log_probs(logits, torch.tensor([3, 3]), ids, temperature=2.0)
    q = torch.tensor([1.0, 2.0, 5.0]).sqrt()
    assert torch.allclose(logp2, (q[0] / q.sum()).log().expand(2), atol=1e-6)
    with pytest.raises(ValueError, match="not one of"):
        action_log_probs(logits, torch.tensor([0, 3]), ids, temperature=1.0)
