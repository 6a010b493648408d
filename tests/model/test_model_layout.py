"""model/layout.py: `SequenceLayout`, the training and the inference layout on hand-checked tensors; the length
groups, their plan (hand-checked, optimal against brute force) and the grouped decoder stack equal to one call
(hidden states, the agent's loss and gradients).

Embeddings are one number per token (D = 1) naming it: BOS 1, prompt 2-5, action 4 / 6 / 7, memory 10-13,
current frame 20-23, BOX 30-31, padding 0.
"""

from __future__ import annotations

import dataclasses
import itertools
import random

import pytest
import torch

from openfly_agent.model.layout import (
    MIN_SAVING,
    PADDING_LEFT,
    PADDING_RIGHT,
    SequenceLayout,
    last_true_index,
    plan_length_groups,
    position_ids_from_mask,
    run_in_length_groups,
)

X = -100  # IGNORE_INDEX


def _col(values) -> torch.Tensor:
    """(L,) or (B, L) numbers -> (..., L, 1) float embeddings."""
    return torch.tensor(values, dtype=torch.float32)[..., None]


def _training(box: bool = True) -> SequenceLayout:
    # [BOS] prompt action pad: row 0 acts 4, row 1 acts 6 then 7
    text = _col([[1, 2, 3, 4, 0], [1, 5, 6, 7, 0]])
    mask = torch.tensor([[1, 1, 1, 1, 0], [1, 1, 1, 1, 0]])
    labels = torch.tensor([[X, X, X, 4, X], [X, X, 6, 7, X]])
    memory = _col([[10, 11], [12, 13]])
    memory_mask = torch.tensor([[True, False], [True, True]])  # row 0's second memory set is missing
    current = _col([[20, 21], [22, 23]])
    return SequenceLayout.for_training(
        text, mask, labels, memory, memory_mask, current, _col([30, 31]) if box else None
    )


def test_training_layout_right_padded_with_the_box_before_the_action():
    layout = _training()
    assert layout.padding == PADDING_RIGHT
    # [BOS] [memory] [current] [prompt] [BOX] [action] [pad]
    assert layout.embeds[..., 0].tolist() == [
        [1, 10, 11, 20, 21, 2, 3, 30, 4, 0],
        [1, 12, 13, 22, 23, 5, 31, 6, 7, 0],
    ]
    assert layout.mask.tolist() == [[1, 1, 0, 1, 1, 1, 1, 1, 1, 0], [1, 1, 1, 1, 1, 1, 1, 1, 1, 0]]
    assert layout.positions.tolist() == [[0, 1, 1, 2, 3, 4, 5, 6, 7, 7], [0, 1, 2, 3, 4, 5, 6, 7, 8, 8]]
    assert layout.labels.tolist() == [[X, X, X, X, X, X, X, X, 4, X], [X, X, X, X, X, X, X, 6, 7, X]]
    # the grounding head reads BOS, attended memory, the frame and the prompt: no missing slot, BOX, target, pad
    assert layout.readable.long().tolist() == [[1, 1, 0, 1, 1, 1, 1, 0, 0, 0], [1, 1, 1, 1, 1, 1, 0, 0, 0, 0]]
    assert layout.first_image.tolist() == [3, 3]
    assert layout.image_positions().tolist() == [[3, 4], [3, 4]]
    assert last_true_index(layout.readable).tolist() == [6, 5]  # the last prompt token
    assert last_true_index(torch.zeros(1, 3, dtype=torch.bool)).tolist() == [0]
    # the action is read at BOX (row 0: -> 4; row 1: -> 6) and after it (row 1: 6 -> 7)
    assert layout.action_reads().long().tolist() == [[0, 0, 0, 0, 0, 0, 0, 1, 0], [0, 0, 0, 0, 0, 0, 1, 1, 0]]
    assert layout.action_targets().tolist() == [4, 6, 7]


def test_training_layout_without_box_token_or_labels():
    layout = _training(box=False)
    assert layout.embeds[..., 0].tolist() == [
        [1, 10, 11, 20, 21, 2, 3, 4, 0],
        [1, 12, 13, 22, 23, 5, 6, 7, 0],
    ]
    grounding = SequenceLayout.for_training(  # a grounding batch: no action label, every text token readable
        _col([[1, 2, 0]]), torch.tensor([[1, 1, 0]]), torch.tensor([[X, X, X]]),
        _col([[]]).reshape(1, 0, 1), torch.zeros(1, 0, dtype=torch.bool), _col([[20]]),
    )  # fmt: skip
    assert grounding.embeds[..., 0].tolist() == [[1, 20, 2, 0]]
    assert grounding.readable.long().tolist() == [[1, 1, 1, 0]]


def test_inference_layout_left_padded_then_one_cached_step():
    prompts = [_col([1, 2, 3]), _col([1, 5])]  # [BOS] prompt of each episode
    memories = [_col([10]), _col([])]  # one memory token, none
    layout = SequenceLayout.for_inference(prompts, memories, _col([[20, 21], [22, 23]]))
    assert layout.padding == PADDING_LEFT and layout.labels is None
    assert layout.embeds[..., 0].tolist() == [[1, 10, 20, 21, 2, 3], [0, 0, 1, 22, 23, 5]]
    assert layout.mask.tolist() == [[1, 1, 1, 1, 1, 1], [0, 0, 1, 1, 1, 1]]
    assert layout.positions.tolist() == [[0, 1, 2, 3, 4, 5], [0, 0, 0, 1, 2, 3]]
    assert layout.readable.long().tolist() == layout.mask.tolist()
    assert layout.first_image.tolist() == [2, 3]  # after [pad] [BOS] [memory]
    box = layout.then(_col([30, 31]))  # [BOX] after every row, read against the prefill's cache
    assert box.embeds[..., 0].tolist() == [[30], [31]]
    assert box.mask.tolist() == [[1, 1, 1, 1, 1, 1, 1], [0, 0, 1, 1, 1, 1, 1]]
    assert box.positions.tolist() == [[6], [4]]
    assert box.then(_col([4, 6])).positions.tolist() == [[7], [5]]


def test_training_and_inference_place_the_same_tokens_at_the_same_positions():
    """Row 0 of the training layout (its missing memory slot dropped, no action) and the same step at inference."""
    train = _training()
    inference = SequenceLayout.for_inference(
        [_col([1, 2, 3]), _col([1, 5])], [_col([10]), _col([12, 13])], _col([[20, 21], [22, 23]])
    )
    for row in range(2):
        kept = train.mask[row].bool() & (train.labels[row] == X)  # attended, not the action
        kept[train.embeds[row, :, 0] >= 30] = False  # BOX follows the prefill at inference
        attended = inference.mask[row].bool()
        assert torch.equal(train.embeds[row][kept], inference.embeds[row][attended])
        assert torch.equal(train.positions[row][kept], inference.positions[row][attended])
        first = train.first_image[row] - (~train.mask[row, : train.first_image[row]].bool()).sum()
        padding = (~attended).sum()
        assert int(first) == int(inference.first_image[row] - padding)  # the frame after the same tokens


def test_the_prompt_mask_is_the_readable_positions_after_the_frame_in_training_and_inference():
    train = _training()  # row 0's prompt: 2, 3 (its action 4 and BOX after it); row 1's: 5
    assert train.embeds[..., 0][train.prompt_mask()].tolist() == [2.0, 3.0, 5.0]
    inference = SequenceLayout.for_inference(
        [_col([1, 2, 3]), _col([1, 5])], [_col([10]), _col([])], _col([[20, 21], [22, 23]])
    )  # left padding, BOS and memory before the frame: none of them counted
    assert inference.embeds[..., 0][inference.prompt_mask()].tolist() == [2.0, 3.0, 5.0]


# --- length groups ----------------------------------------------------------------------------------------
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
