"""The grounding head's cells beyond the LLM's hidden states (model/grounding/head.py): `grounding.visual_skip`
(the cells get the frame's visual tokens) and `grounding.colour_match` (the cells' colour histograms against the
colours asked for by the query and the prompt's words)."""

from __future__ import annotations

import math

import pytest
import torch

from openfly_agent.model.config import BoxGroundingConfig, CellGroundingConfig
from openfly_agent.model.grounding.head import CellGroundingHead, ColourMatch

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


# --- the colour match ------------------------------------------------------------------------------------------
RED, BLUE, GRAY = (255, 0, 0), (0, 0, 255), (128, 128, 128)


def _red_blue_match() -> ColourMatch:
    """A 2-class match on a 2 x 2 grid whose pixel classifier is set by hand: hidden 0 = 10 (R - B), hidden 1 =
    10 (B - R) (R, B scaled to [-0.5, 0.5]), class k's logit = GELU(hidden k). A red pixel: logits (10, ~0),
    class 0; a blue one: class 1; a gray one: (0, 0), half and half."""
    match = ColourMatch(dim=2, llm_dim=3, classes=2, grid_side=2)
    with torch.no_grad():
        first, second = match.pixel_classes[0], match.pixel_classes[2]
        first.weight.zero_()
        first.bias.zero_()
        first.weight[0, :, 0, 0] = torch.tensor([10.0, 0.0, -10.0])
        first.weight[1, :, 0, 0] = torch.tensor([-10.0, 0.0, 10.0])
        second.weight.zero_()
        second.bias.zero_()
        second.weight[0, 0, 0, 0] = second.weight[1, 1, 0, 0] = 1.0
    return match


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


def test_the_colour_histogram_is_each_cells_share_of_pixels_per_class():
    match = _red_blue_match()
    frame = _frame([[RED, BLUE], [GRAY, GRAY]], red_pixels=4)  # the last cell: 4 red pixels of 16
    with torch.no_grad():
        shares = match.histogram(frame)  # (1, 4, 2)
    # red: class 0 at softmax(10 - GELU(-10)) = 0.99995; gray: 0.5 / 0.5; the last cell 4 / 16 red
    expected = torch.tensor([[[1.0, 0.0], [0.0, 1.0], [0.5, 0.5], [0.25 + 0.75 * 0.5, 0.75 * 0.5]]])
    torch.testing.assert_close(shares, expected, atol=1e-3, rtol=0)
    torch.testing.assert_close(shares.sum(dim=-1), torch.ones(1, 4))


def test_the_match_is_the_weighted_log_of_the_share_in_the_asked_colour():
    match = _red_blue_match()
    with torch.no_grad():
        match.query_classes.weight.copy_(torch.eye(2))
        match.query_classes.bias.zero_()
        match.word_classes.weight.zero_()  # the query alone asks
        match.weight.fill_(2.0)
    colours = torch.tensor([[[0.9, 0.1], [0.0, 1.0], [0.5, 0.5]]])  # (1, 3, 2)
    code = torch.tensor([[math.log(3.0), 0.0]])  # asks for class 0 with 3 / 4, class 1 with 1 / 4
    with torch.no_grad():
        logits = match(colours, code, torch.randn(1, 3))  # (1, 3)
    shares = [0.75 * 0.9 + 0.25 * 0.1, 0.25 * 1.0, 0.5]  # 0.7, 0.25, 0.5
    expected = torch.tensor([[2.0 * math.log(share + 1e-3) for share in shares]])
    torch.testing.assert_close(logits, expected)


def test_the_prompts_words_join_the_ask():
    match = _red_blue_match()
    with torch.no_grad():
        match.query_classes.weight.zero_()
        match.query_classes.bias.zero_()
        match.word_classes.weight.zero_()
        match.word_classes.weight[1, 2] = (
            1.0  # the third embedding dimension (a "blue" word) asks for class 1
        )
        words = torch.tensor([[0.0, 0.0, math.log(3.0)]])
        torch.testing.assert_close(match.ask(torch.randn(1, 2), words), torch.tensor([[0.25, 0.75]]))
        torch.testing.assert_close(
            match.ask(torch.randn(1, 2), torch.zeros(1, 3)), torch.tensor([[0.5, 0.5]])
        )


def test_the_colour_match_moves_only_the_cells_whose_colours_changed():
    torch.manual_seed(0)
    cfg = CellGroundingConfig(dim=8, num_heads=2, colour_match=4)
    head = CellGroundingHead(16, cfg, grid_side=2).eval()
    head.init_weights()
    hidden = torch.randn(1, 7, 16)
    frame = _frame([[GRAY, GRAY], [GRAY, GRAY]])
    red = _frame([[GRAY, GRAY], [GRAY, GRAY]], red_pixels=3)  # 3 red pixels in the last cell
    words = torch.randn(1, 16)
    with torch.no_grad():
        plain, with_red = (
            head(
                hidden, KEY_MASK, IMAGE_POSITIONS, LAST_PROMPT, None, head.colour_match.histogram(f), words
            ).cell_logits
            for f in (frame, red)
        )
    moved = (with_red - plain).abs()[0]  # (4,)
    assert moved[3] > 1e-3 and moved[:3].tolist() == [0.0, 0.0, 0.0]
    with pytest.raises(ValueError, match="colour_match needs the current frame's cell colours"):
        head(hidden, KEY_MASK, IMAGE_POSITIONS, LAST_PROMPT)


def test_without_the_colour_match_the_state_dict_is_that_of_earlier_checkpoints():
    assert not any(name.startswith("colour_match") for name in _head().state_dict())


@pytest.mark.parametrize("classes", [-1, 1])
def test_the_colour_match_needs_two_classes_or_none(classes):
    with pytest.raises(ValueError, match="colour_match"):
        CellGroundingConfig(colour_match=classes)
