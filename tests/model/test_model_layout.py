"""`SequenceLayout` (model/layout.py): the training and the inference layout on hand-checked tensors.

Embeddings are one number per token (D = 1) naming it: BOS 1, prompt 2-5, action 4 / 6 / 7, memory 10-13,
current frame 20-23, BOX 30-31, padding 0.
"""

from __future__ import annotations

import torch

from openfly_agent.model.layout import PADDING_LEFT, PADDING_RIGHT, SequenceLayout

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
