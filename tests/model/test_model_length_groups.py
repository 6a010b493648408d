"""model/language/length_groups.py: the grouping plan (hand-checked, optimal against brute force) and the grouped decoder
stack equal to one call (hidden states, the agent's loss and gradients)."""

from __future__ import annotations

import dataclasses
import itertools
import random

import pytest
import torch

from openfly_agent.model.language.length_groups import MIN_SAVING, plan_length_groups, run_in_length_groups


def cost(lengths: list[int], groups: list[list[int]]) -> int:
    return sum(len(rows) * max(lengths[row] for row in rows) for rows in groups)


def test_two_kinds_of_rows_make_two_groups():
    # padded: 4 x 100 = 400 tokens; grouped: 2 x 12 + 2 x 100 = 224
    assert plan_length_groups([10, 100, 12, 98], 2) == [[0, 2], [3, 1]]
    assert cost([10, 100, 12, 98], [[0, 2], [3, 1]]) == 224


def test_one_group_when_the_saving_is_small_or_not_allowed():
    assert plan_length_groups([95, 100], 2) == [[0, 1]]  # saves 5 of 200 tokens, under MIN_SAVING
    assert MIN_SAVING > 5 / 200
    assert plan_length_groups([10, 100, 12, 98], 1) == [[0, 2, 3, 1]]
    assert plan_length_groups([], 3) == []
    with pytest.raises(ValueError, match="max_groups"):
        plan_length_groups([3], 0)


def test_the_plan_is_an_optimal_partition_of_the_sorted_rows():
    rng = random.Random(0)
    for _ in range(200):
        lengths = [rng.randint(1, 60) for _ in range(rng.randint(1, 7))]
        max_groups = rng.randint(1, 3)
        groups = plan_length_groups(lengths, max_groups)
        assert sorted(row for rows in groups for row in rows) == list(range(len(lengths)))
        assert 1 <= len(groups) <= max_groups
        # the best of every split of the sorted rows into at most max_groups runs
        order = sorted(range(len(lengths)), key=lambda row: (lengths[row], row))
        best = min(
            cost(lengths, [order[a:b] for a, b in zip((0, *cuts), (*cuts, len(order)))])
            for k in range(max_groups)
            for cuts in itertools.combinations(range(1, len(order)), k)
        )
        padded = len(lengths) * max(lengths)
        assert best <= cost(lengths, groups)
        # a further group is dropped only when it would have saved less than MIN_SAVING of the padded batch
        assert cost(lengths, groups) - best < MIN_SAVING * padded


def tiny_llama():
    from transformers import LlamaConfig, LlamaModel

    torch.manual_seed(0)
    config = LlamaConfig(
        vocab_size=32, hidden_size=32, intermediate_size=64, num_hidden_layers=2, num_attention_heads=2
    )
    config._attn_implementation = "sdpa"
    return LlamaModel(config).eval()


def test_grouped_hidden_states_and_gradients_equal_one_call():
    from openfly_agent.model.layout import position_ids_from_mask

    model = tiny_llama()

    def run(embeds, mask):
        return model(inputs_embeds=embeds, attention_mask=mask, position_ids=position_ids_from_mask(mask))[0]

    lengths = [5, 40, 7, 38, 6]
    mask = torch.zeros(5, 40, dtype=torch.long)
    for row, length in enumerate(lengths):
        mask[row, :length] = 1
    mask[1, 3:5] = 0  # a hole, as a missing memory slot leaves
    embeds = torch.randn(5, 40, 32, requires_grad=True)
    assert len(plan_length_groups(lengths, 2)) == 2

    single = run(embeds, mask)
    (single_grad,) = torch.autograd.grad((single * mask[..., None]).square().sum(), embeds)
    grouped = run_in_length_groups(run, embeds, mask, 2)
    (grouped_grad,) = torch.autograd.grad((grouped * mask[..., None]).square().sum(), embeds)

    real = mask.bool()
    torch.testing.assert_close(grouped[real], single[real], atol=1e-5, rtol=1e-4)
    torch.testing.assert_close(grouped_grad, single_grad, atol=1e-5, rtol=1e-4)
    assert bool((grouped[0, 7:] == 0).all())  # past the longest row of its group (7): zeros
    assert run_in_length_groups(run, embeds, mask, 1).shape == single.shape


def _counting(run_llm, calls: list):
    """`run_llm` that also appends the shape of each call's embeddings to `calls`."""

    def run(embeds, *args, **kwargs):
        calls.append(embeds.shape)
        return run_llm(embeds, *args, **kwargs)

    return run


def test_the_agent_loss_and_gradients_do_not_depend_on_the_grouping(make_agent, make_batch, small_config):
    from openfly_agent.model.config import LLMConfig

    base = dataclasses.replace(small_config().llm, length_groups=1)
    grouped_llm = dataclasses.replace(base, length_groups=2)
    assert isinstance(grouped_llm, LLMConfig)
    results = []
    for llm in (base, grouped_llm):
        agent = make_agent(seed=3, llm=llm)
        batch = make_batch(agent, batch_size=4, seed=1)
        calls = []
        agent.network.run_llm = _counting(agent.network.run_llm, calls)
        loss, logs = agent(batch)
        assert len(calls) == llm.length_groups  # the second instruction is much shorter: two groups
        loss.backward()
        grads = {name: p.grad.clone() for name, p in agent.named_parameters() if p.grad is not None}
        results.append((loss.detach(), logs, grads))
    (loss_1, logs_1, grads_1), (loss_2, logs_2, grads_2) = results
    torch.testing.assert_close(loss_2, loss_1, atol=1e-5, rtol=1e-5)
    assert logs_2["action_accuracy"] == logs_1["action_accuracy"]
    assert grads_1.keys() == grads_2.keys()
    for name, grad in grads_1.items():
        torch.testing.assert_close(grads_2[name], grad, atol=1e-5, rtol=1e-4, msg=name)


def test_the_tiny_preset_groups_and_the_7b_presets_keep_one_call():
    from openfly_agent.model.config import openfly_7b_config, openvla_compat_7b_config, tiny_config

    assert tiny_config().llm.length_groups == 3
    assert openfly_7b_config().llm.length_groups == 1
    assert openvla_compat_7b_config().llm.length_groups == 1
