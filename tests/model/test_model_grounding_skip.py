"""The grounding head's cells beyond the LLM's hidden states (model/grounding/head.py): `grounding.visual_skip`
(the cells get the frame's visual tokens) and `grounding.colour_vocabulary` (the cells' colour histograms against
the classes asked for by the colour the prompt's words name)."""

from __future__ import annotations

import math

import pytest
import torch

from openfly_agent.model.config import BoxGroundingConfig, CellGroundingConfig
from openfly_agent.model.grounding.head import (
    CellGroundingHead,
    ColourVocabulary,
    grounding_loss,
    word_colour_loss,
)
from openfly_agent.model.grounding.layers import GroundingOutput

# a 2 x 2 grid at positions 1-4 of a 7-position sequence; position 5 is a prompt token, 6 padding (not readable)
IMAGE_POSITIONS = torch.tensor([[1, 2, 3, 4]])
LAST_PROMPT = torch.tensor([5])
KEY_MASK = torch.tensor([[True, True, True, True, True, True, False]])


def _head(visual_skip: bool = False) -> CellGroundingHead:
    torch.manual_seed(0)
    cfg = CellGroundingConfig(dim=8, num_heads=2, attribute_weight=1.0, visual_skip=visual_skip)
    return CellGroundingHead(16, cfg, grid_side=2).eval()


def _cell_side(
    head: CellGroundingHead, hidden: torch.Tensor, visual: torch.Tensor | None = None
) -> torch.Tensor:
    """(1, 4, A) attribute logits of the cells: what the cell side holds, before the query's FiLM."""
    with torch.no_grad():
        return head(hidden, KEY_MASK, IMAGE_POSITIONS, LAST_PROMPT, visual).cell_attributes


def test_the_visual_skip_adds_each_cells_own_visual_token():
    hidden, visual = torch.randn(1, 7, 16), torch.randn(1, 4, 16)
    head = _head(visual_skip=True)
    changed = visual.clone()
    changed[0, 2] += 3.0  # the third cell's token only
    moved = (_cell_side(head, hidden, changed) - _cell_side(head, hidden, visual)).abs().sum(dim=-1)  # (1, 4)
    assert moved[0, 2] > 0 and moved[0, [0, 1, 3]].tolist() == [0.0, 0.0, 0.0]
    with torch.no_grad():  # a zero projection leaves the cells as without the skip
        head.visual_proj.weight.zero_()
        head.visual_proj.bias.zero_()
    zero_skip = _cell_side(head, hidden, visual)
    with pytest.raises(ValueError, match="visual_skip needs the current frame's visual tokens"):
        _cell_side(head, hidden)
    head.visual_proj = None  # the same weights without the skip
    torch.testing.assert_close(zero_skip, _cell_side(head, hidden))


def test_without_the_skip_the_state_dict_is_that_of_earlier_checkpoints():
    assert not any(name.startswith("visual_proj") for name in _head().state_dict())


def test_the_skip_is_a_field_of_the_cell_head_only():
    with pytest.raises(TypeError, match="visual_skip"):
        BoxGroundingConfig(visual_skip=True)


# --- the colour vocabulary -------------------------------------------------------------------------------------
RED, BLUE, GRAY = (255, 0, 0), (0, 0, 255), (128, 128, 128)


def _red_blue_vocabulary() -> ColourVocabulary:
    """2 named colours (red, blue) and the no-colour class on a 2 x 2 grid, the pixel classifier set by hand:
    hidden 0 = 0.1 (R - B), hidden 1 = 0.1 (B - R) (R, B scaled to [-5, 5], the GAIN of 10), class k's logit =
    10 GELU(hidden k) for the two colours, 0 for none. A red pixel: hidden (1, -1), logits (8.4, -1.6, 0), red at
    0.9998; a blue one: blue; a gray one: (0, 0, 0), a third each."""
    vocabulary = ColourVocabulary(llm_dim=3, colours=2, grid_side=2)
    with torch.no_grad():
        first, second = vocabulary.pixel_classes[0], vocabulary.pixel_classes[2]
        first.weight.zero_()
        first.bias.zero_()
        first.weight[0, :, 0, 0] = torch.tensor([0.1, 0.0, -0.1])
        first.weight[1, :, 0, 0] = torch.tensor([-0.1, 0.0, 0.1])
        second.weight.zero_()
        second.bias.zero_()
        second.weight[0, 0, 0, 0] = second.weight[1, 1, 0, 0] = 1.0
    return vocabulary


def _frame(cells: list[list[tuple[int, int, int]]], red_pixels: int = 0) -> torch.Tensor:
    """(1, 3, 8, 8) uint8: each 4 x 4 cell of the 2 x 2 grid in one colour; the first `red_pixels` pixels of the
    last cell's top row made red."""
    frame = torch.zeros(1, 3, 8, 8, dtype=torch.uint8)
    for row in range(2):
        for col in range(2):
            frame[0, :, 4 * row : 4 * row + 4, 4 * col : 4 * col + 4] = torch.tensor(cells[row][col])[
                :, None, None
            ]
    frame[0, :, 4, 4 : 4 + red_pixels] = torch.tensor(RED)[:, None]
    return frame


def test_the_colour_histogram_is_each_cells_share_of_pixels_per_named_colour_and_none():
    vocabulary = _red_blue_vocabulary()
    frame = _frame([[RED, BLUE], [GRAY, GRAY]], red_pixels=4)  # the last cell: 4 red pixels of 16
    with torch.no_grad():
        shares = vocabulary.histogram(frame)  # (1, 4, 3)
    # red: softmax(8.4, -1.6, 0) = 0.9998 red; gray: a third each; the last cell 4 / 16 red, 12 / 16 gray
    third = 1.0 / 3.0
    expected = torch.tensor(
        [[[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [third, third, third], [0.25 + 0.75 * third, 0.25, 0.25]]]
    )
    torch.testing.assert_close(shares, expected, atol=1e-3, rtol=0)
    torch.testing.assert_close(shares.sum(dim=-1), torch.ones(1, 4))


def test_the_match_is_the_weighted_log_of_the_share_in_the_named_colour():
    vocabulary = _red_blue_vocabulary()
    with torch.no_grad():
        vocabulary.weight.fill_(2.0)
    colours = torch.tensor([[[0.7, 0.1, 0.2], [0.0, 1.0, 0.0], [0.25, 0.25, 0.5]]])  # (1, 3, 3)
    with torch.no_grad():
        red = vocabulary(colours, torch.tensor([[30.0, 0.0]]))  # red named: the cells' red shares
        both = vocabulary.ask(torch.zeros(1, 2))  # both at 1 / 2, none never asked
    expected = torch.tensor([[2.0 * math.log(share + 1e-3) for share in (0.7, 0.0, 0.25)]])
    torch.testing.assert_close(red, expected)
    torch.testing.assert_close(both, torch.tensor([[0.5, 0.5, 0.0]]))


def test_the_words_are_pooled_by_their_scores_and_the_last_word_wins_with_the_place_term():
    vocabulary = ColourVocabulary(llm_dim=4, colours=2, grid_side=2)
    red_word, blue_word, other = (
        torch.eye(4)[0],
        torch.eye(4)[1],
        torch.eye(4)[2],
    )  # normalised: 2 x unit vectors
    words = torch.stack([red_word, other, blue_word, other, other])[None]  # (1, 5, 4): "red ... blue ..."
    mask = torch.tensor([[True, True, True, True, False]])  # the last position is not the prompt's
    with torch.no_grad():
        vocabulary.word_colours.weight.copy_(torch.tensor([[1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0]]))
        vocabulary.word_colours.bias.zero_()
        vocabulary.word_score.weight.zero_()
        vocabulary.word_score.weight[0, :2] = (
            10.0  # colour words score 20 (x 2, the normalised scale): content
        )
        plain = vocabulary.name_colour(words, mask)
        vocabulary.word_score.weight[1, 1] = 10.0  # the blue word, the later one, gains 20 x its place 3 / 4
        placed = vocabulary.name_colour(words, mask)
        none = vocabulary.name_colour(words, torch.zeros(1, 5, dtype=torch.bool))
    # content only: the two colour words share the pool (e^20 each against e^0), each logit about 2 / 2 = 1
    torch.testing.assert_close(plain, torch.tensor([[1.0, 1.0]]), atol=1e-6, rtol=0)
    # with the place term: blue's score 20 + 15, red's 20 + 0: the pool is blue's word (x 2)
    torch.testing.assert_close(placed, torch.tensor([[0.0, 2.0]]), atol=1e-5, rtol=0)
    torch.testing.assert_close(none, torch.zeros(1, 2))  # no words: the bias


def test_the_word_colour_loss_skips_unknown_colours_and_is_the_cross_entropy_of_the_rest():
    logits = torch.tensor([[2.0, 0.0], [0.0, 0.0], [5.0, 0.0]], requires_grad=True)
    attributes = torch.tensor([[0, 1, 0, 0], [1, 0, 0, 0], [-1, 2, 1, 0]])
    term, logs = word_colour_loss(logits, attributes)
    expected = (math.log(1 + math.exp(-2.0)) + math.log(2.0)) / 2  # rows 0 and 1
    assert term.item() == pytest.approx(expected)
    assert logs["word_color_accuracy"] == 0.5  # row 0 right, row 1 a tie read as colour 0
    term, logs = word_colour_loss(logits, torch.full((3, 4), -1))
    assert term.item() == 0.0 and "word_color_accuracy" not in logs
    term.backward()  # in the graph with no known colour
    assert logits.grad is not None


def test_the_colour_vocabulary_moves_only_the_cells_whose_colours_changed_and_names_a_colour():
    torch.manual_seed(0)
    cfg = CellGroundingConfig(dim=8, num_heads=2, colour_vocabulary=True)
    head = CellGroundingHead(16, cfg, grid_side=2).eval()
    head.init_weights()
    hidden, words = torch.randn(1, 7, 16), torch.randn(1, 7, 16)
    word_mask = torch.tensor([[False, False, False, False, False, True, False]])  # position 5: the prompt
    frame = _frame([[GRAY, GRAY], [GRAY, GRAY]])
    red = _frame([[GRAY, GRAY], [GRAY, GRAY]], red_pixels=3)  # 3 red pixels in the last cell
    with torch.no_grad():
        plain, with_red = (
            head(
                hidden,
                KEY_MASK,
                IMAGE_POSITIONS,
                LAST_PROMPT,
                None,
                head.colour_vocabulary.histogram(f),
                words,
                word_mask,
            )
            for f in (frame, red)
        )
    moved = (with_red.cell_logits - plain.cell_logits).abs()[0]  # (4,)
    assert moved[3] > 1e-3 and moved[:3].tolist() == [0.0, 0.0, 0.0]
    torch.testing.assert_close(
        with_red.match_logits - plain.match_logits, with_red.cell_logits - plain.cell_logits
    )
    assert plain.word_colours.shape == (1, cfg.attribute_classes[0])
    with pytest.raises(ValueError, match="colour_vocabulary needs the current frame's cell colours"):
        head(hidden, KEY_MASK, IMAGE_POSITIONS, LAST_PROMPT)


def test_without_the_colour_vocabulary_the_state_dict_is_that_of_earlier_checkpoints():
    assert not any(name.startswith("colour_vocabulary") for name in _head().state_dict())


def test_the_colour_cell_loss_is_the_cross_entropy_of_the_target_cell_from_the_match_alone():
    match = torch.tensor([[0.0, 0.0, 0.0, math.log(3.0)], [5.0, 0.0, 0.0, 0.0]])  # (2, 4): row 1 not visible
    output = GroundingOutput(
        boxes=torch.full((2, 4), 0.5),
        visibility=torch.zeros(2),
        cell_logits=torch.zeros(2, 4),
        match_logits=match,
    )
    target = torch.tensor([[0.75, 0.75, 0.2, 0.2], [0.25, 0.25, 0.2, 0.2]])  # row 0 in cell 3
    _, logs = grounding_loss(output, target, torch.tensor([True, False]), CellGroundingConfig())
    assert logs["colour_cell_loss"] == pytest.approx(math.log(2.0))  # -log(3 / (1 + 1 + 1 + 3))
    _, logs = grounding_loss(output, target, torch.tensor([False, False]), CellGroundingConfig())
    assert logs["colour_cell_loss"] == 0.0
