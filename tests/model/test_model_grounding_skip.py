"""The grounding head's cells beyond the LLM's hidden states (model/grounding/head.py): `grounding.visual_skip`
(the cells get the frame's visual tokens)."""

from __future__ import annotations

import pytest
import torch

from openfly_agent.model.config import BoxGroundingConfig, CellGroundingConfig
from openfly_agent.model.grounding.head import CellGroundingHead

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
