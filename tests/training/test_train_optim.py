"""Optimizer parameter groups, the lr schedules (hand-checked values) and the epoch samplers."""

from __future__ import annotations

import math

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from torch import nn

from openfly_agent.training.optim import (
    ScheduleClock,
    lr_multiplier,
    make_optimizer,
    make_param_groups,
    make_scheduler,
)
from openfly_agent.training.sampler import EpochShuffleSampler


def _net() -> nn.Module:
    net = nn.Sequential(nn.Linear(4, 8), nn.LayerNorm(8), nn.Linear(8, 2))
    net[2].weight.requires_grad_(False)
    return net


def test_param_groups_decay_matrices_only_and_skip_frozen():
    net = _net()
    groups = make_param_groups(net, weight_decay=0.1)
    decayed = [p for g in groups if g["weight_decay"] == 0.1 for p in g["params"]]
    undecayed = [p for g in groups if g["weight_decay"] == 0.0 for p in g["params"]]
    assert [p.shape for p in decayed] == [torch.Size([8, 4])]
    assert {id(p) for p in undecayed} == {
        id(net[0].bias),
        id(net[1].weight),
        id(net[1].bias),
        id(net[2].bias),
    }
    assert all(p is not net[2].weight for g in groups for p in g["params"])


def test_param_groups_keep_model_options():
    net = _net()
    net.get_optim_params = lambda: [
        {"params": list(net[0].parameters()), "lr": 1e-5},
        {"params": net[1:].parameters()},
    ]
    groups = make_param_groups(net, weight_decay=0.0)
    assert [g.get("lr") for g in groups] == [1e-5, 1e-5, None]


def test_no_trainable_parameters_is_an_error():
    net = nn.Linear(2, 2).requires_grad_(False)
    with pytest.raises(ValueError, match="no trainable parameters"):
        make_param_groups(net, 0.0)


def test_schedules_hand_checked():
    # warmup 2 steps: 1/3, 2/3, then the schedule proper over the remaining 8 of 10 steps.
    assert lr_multiplier(0, "constant", 2, 10) == pytest.approx(1 / 3)
    assert lr_multiplier(1, "constant", 2, 10) == pytest.approx(2 / 3)
    assert lr_multiplier(7, "constant", 2, 10) == 1.0
    assert lr_multiplier(2, "cosine", 2, 10) == pytest.approx(1.0)
    assert lr_multiplier(6, "cosine", 2, 10) == pytest.approx(0.5)  # half-way: cos(pi/2) = 0
    assert lr_multiplier(10, "cosine", 2, 10) == pytest.approx(0.0, abs=1e-12)
    assert lr_multiplier(6, "linear", 2, 10) == pytest.approx(0.5)
    assert lr_multiplier(6, "linear", 2, 10, min_lr_ratio=0.2) == pytest.approx(0.6)
    assert lr_multiplier(50, "linear", 2, 10) == 0.0  # past the end it stays at the floor
    with pytest.raises(ValueError, match="optim.schedule"):
        lr_multiplier(0, "exp", 0, 10)


@settings(max_examples=60, deadline=None)
@given(st.integers(0, 50), st.integers(0, 20), st.integers(1, 100), st.sampled_from(["cosine", "linear"]))
def test_decaying_schedules_stay_in_range_and_never_rise_after_warmup(step, warmup, total, schedule):
    value = lr_multiplier(step, schedule, warmup, total)
    assert 0.0 <= value <= 1.0
    if step >= warmup:
        assert lr_multiplier(step + 1, schedule, warmup, total) <= value + 1e-12


def test_scheduler_drives_optimizer_lr():
    net = _net()
    opt = make_optimizer(net, lr=1.0, weight_decay=0.0, betas=(0.9, 0.99))
    sched = make_scheduler(opt, "cosine", warmup_steps=0, total_steps=4)
    lrs = []
    for _ in range(4):
        lrs.append(opt.param_groups[0]["lr"])
        opt.step()
        sched.step()
    assert lrs == pytest.approx(
        [1.0, 0.5 * (1 + math.cos(math.pi / 4)), 0.5, 0.5 * (1 + math.cos(3 * math.pi / 4))]
    )


def test_a_time_fraction_moves_the_decay_to_the_further_of_the_two_budgets():
    # warmup 2 of 10 steps; at step 2 the step budget has not started decaying, half the time is used
    assert lr_multiplier(2, "cosine", 2, 10, time_fraction=0.5) == pytest.approx(0.5)
    assert lr_multiplier(2, "linear", 2, 10, min_lr_ratio=0.2, time_fraction=0.25) == pytest.approx(0.8)
    # step 8 is 3/4 of the decay: the steps are further along than a quarter of the time
    assert lr_multiplier(8, "linear", 2, 10, time_fraction=0.25) == pytest.approx(0.25)
    assert lr_multiplier(3, "cosine", 2, 10, min_lr_ratio=0.1, time_fraction=1.0) == pytest.approx(0.1)
    assert lr_multiplier(0, "cosine", 2, 10, time_fraction=0.9) == pytest.approx(1 / 3)  # warmup is in steps
    assert lr_multiplier(5, "constant", 2, 10, time_fraction=0.9) == 1.0


def test_a_scheduler_with_a_clock_follows_the_used_time():
    net = _net()
    opt = make_optimizer(net, lr=1.0, weight_decay=0.0, betas=(0.9, 0.99))
    clock = ScheduleClock()
    sched = make_scheduler(opt, "linear", warmup_steps=0, total_steps=1000, clock=clock)
    lrs = []
    for fraction in (0.25, 0.5, 1.0):
        clock.fraction = fraction
        opt.step()
        sched.step()
        lrs.append(opt.param_groups[0]["lr"])
    assert lrs == pytest.approx([0.75, 0.5, 0.0])


def test_sampler_order_depends_only_on_seed_and_epoch():
    a, b = EpochShuffleSampler(23, 4, seed=7), EpochShuffleSampler(23, 4, seed=7)
    assert len(a) == 20 and a.steps_per_epoch == 5
    assert list(a) == list(b)
    first = list(a)
    a.set_epoch(1)
    assert list(a) != first
    b.set_epoch(1)
    assert list(a) == list(b)
    assert len(set(first)) == 20 and set(first) <= set(range(23))
    assert list(EpochShuffleSampler(23, 4, seed=8)) != first


def test_sampler_rejects_dataset_smaller_than_a_global_batch():
    with pytest.raises(ValueError, match="fewer than one global batch"):
        EpochShuffleSampler(3, 4, seed=0)


def test_fused_adamw_is_off_by_default_and_steps_as_the_default_kernel():
    from openfly_agent.training.config import OptimConfig

    assert OptimConfig().fused_adamw is False
    torch.manual_seed(0)
    nets = [_net(), _net()]
    nets[1].load_state_dict(nets[0].state_dict())
    default = make_optimizer(nets[0], lr=0.1, weight_decay=0.01, betas=(0.9, 0.95))
    fused = make_optimizer(nets[1], lr=0.1, weight_decay=0.01, betas=(0.9, 0.95), fused=True)
    assert not default.defaults["fused"] and fused.defaults["fused"] is True
    x = torch.randn(3, 4)
    for net, optimizer in zip(nets, (default, fused)):
        for _ in range(3):
            net(x).square().sum().backward()
            optimizer.step()
            optimizer.zero_grad()
    for a, b in zip(nets[0].parameters(), nets[1].parameters()):
        torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-6)
