"""The grounding head's attribute loss and attribute match (model/grounding/head.py), checked by hand on tiny logits."""

from __future__ import annotations

import math

import pytest
import torch

from openfly_agent.model.config import GroundingConfig
from openfly_agent.model.grounding.cells import CellGroundingHead, attribute_match, fine_grid
from openfly_agent.model.grounding.head import GroundingOutput, attribute_loss, grounding_loss

CFG = GroundingConfig(dim=8, num_heads=2, attribute_weight=2.0, attribute_classes=[2, 2, 2, 2])


def _output(query: torch.Tensor, cells: torch.Tensor) -> GroundingOutput:
    """Two rows on a 2 x 2 grid; boxes and cell logits do not enter the attribute term."""
    return GroundingOutput(
        boxes=torch.full((2, 4), 0.5), visibility=torch.zeros(2), cell_logits=torch.zeros(2, 4),
        query_attributes=query, cell_attributes=cells,
    )  # fmt: skip


def test_attribute_loss_by_hand():
    # query logits: every attribute of row 0 says class 0 with logit 1 (vs 0); row 1 is all zeros
    query = torch.tensor([[1.0, 0.0] * 4, [0.0, 0.0] * 4])
    # cell logits (2 rows, 4 cells, 8): only the cell under each target's centre matters
    cells = torch.zeros(2, 4, 8)
    cells[0, 3] = torch.tensor([0.0, 2.0] * 4)  # row 0's target centre (0.75, 0.75) is in cell 3
    boxes = torch.tensor([[0.75, 0.75, 0.2, 0.2], [0.25, 0.25, 0.2, 0.2]])
    visible = torch.tensor([True, False])  # row 1's cell is not read
    labels = torch.tensor([[0, 1, 0, -1], [1, -1, -1, -1]])
    term, logs = attribute_loss(_output(query, cells), boxes, visible, labels, CFG)
    p1 = math.log(1 + math.e**-1)  # CE of the right class at logit 1 vs 0
    half = math.log(2)  # CE at equal logits
    q1 = math.log(1 + math.e)  # CE of the wrong class at logit 1 vs 0
    c_right, c_wrong = math.log(1 + math.e**-2), math.log(1 + math.e**2)
    expected = [
        (p1 + half) / 2,  # colour from the query: row 0 right (class 0), row 1 at equal logits
        c_wrong,  # colour from row 0's cell: label 0, the cell says class 1 at 2
        q1,  # type from the query: row 0 only (label 1, logit 1 on class 0)
        c_right,  # type from the cell: label 1
        p1,  # size from the query: row 0, label 0
        c_wrong,  # size from the cell: label 0
    ]  # feature: unknown everywhere, skipped
    assert term.item() == pytest.approx(sum(expected) / len(expected), rel=1e-5)
    assert logs["query_color_accuracy"] == pytest.approx(
        0.5
    )  # row 0 right; row 1 tied -> argmax class 0, wrong
    assert logs["cell_color_accuracy"] == 0.0


def test_grounding_loss_adds_the_weighted_attribute_term_only_with_attributes():
    query, cells = torch.randn(2, 8), torch.randn(2, 4, 8)
    output = _output(query, cells)
    boxes, visible = (
        torch.tensor([[0.75, 0.75, 0.2, 0.2], [0.25, 0.25, 0.2, 0.2]]),
        torch.tensor([True, True]),
    )
    labels = torch.tensor([[0, 1, 0, 1], [1, 0, 1, 0]])
    base, base_logs = grounding_loss(output, boxes, visible, CFG)
    full, logs = grounding_loss(output, boxes, visible, CFG, labels)
    term, _ = attribute_loss(output, boxes, visible, labels, CFG)
    assert "attribute_loss" not in base_logs and logs["attribute_loss"] == pytest.approx(term.item())
    assert full.item() == pytest.approx(base.item() + 2.0 * term.item(), rel=1e-5)
    unknown = torch.full((2, 4), -1)
    none, none_logs = grounding_loss(output, boxes, visible, CFG, unknown)
    assert none.item() == pytest.approx(base.item()) and none_logs["attribute_loss"] == 0.0


def test_attribute_options_are_checked():
    with pytest.raises(ValueError, match="attribute_weight"):
        GroundingConfig(attribute_weight=-1.0)
    with pytest.raises(ValueError, match="attribute_classes"):
        GroundingConfig(attribute_classes=[12, 6, 3])
    with pytest.raises(ValueError, match="needs grounding.cells"):
        GroundingConfig(cells=False, attribute_weight=1.0)
    with pytest.raises(ValueError, match="attribute_match needs"):
        GroundingConfig(attribute_match=True)


def test_attribute_match_by_hand():
    # two attributes of 2 and 3 classes; one row, two cells
    query = torch.tensor(
        [[math.log(3.0), 0.0, 0.0, 0.0, 0.0]]
    )  # attribute 0: (0.75, 0.25); attribute 1: uniform
    cells = torch.zeros(1, 2, 5)
    cells[0, 1, :2] = torch.tensor([0.0, math.log(3.0)])  # cell 1 says class 1 of attribute 0 with p = 0.75
    cells[0, 1, 2:] = torch.tensor([math.log(2.0), 0.0, 0.0])  # and (0.5, 0.25, 0.25) for attribute 1
    weights = torch.tensor([2.0, 1.0])
    match = attribute_match(query, cells, [2, 3], weights)
    cell0 = 2.0 * math.log(0.5) + math.log(1 / 3)  # uniform cell: log 0.5 and log 1/3 whatever the query says
    cell1 = 2.0 * (0.75 * math.log(0.25) + 0.25 * math.log(0.75)) + (math.log(0.5) + 2 * math.log(0.25)) / 3
    assert match.shape == (1, 2)
    assert match[0].tolist() == pytest.approx([cell0, cell1], rel=1e-5)
    assert match[0, 0] > match[0, 1]  # the cell naming the other colour scores lower than an undecided one


def test_fine_grid_repeats_each_cell_over_its_subcells():
    per_cell = torch.tensor([[1.0, 2.0, 3.0, 4.0]])  # 2 x 2 cells
    assert fine_grid(per_cell, 2, 1) is per_cell
    expected = [[1, 1, 2, 2], [1, 1, 2, 2], [3, 3, 4, 4], [3, 3, 4, 4]]
    assert fine_grid(per_cell, 2, 2).view(4, 4).tolist() == expected


def test_the_head_adds_the_weighted_match_to_the_cell_logits():
    torch.manual_seed(0)
    cfg = GroundingConfig(
        dim=8, num_heads=2, attribute_weight=1.0, attribute_classes=[2, 3, 2, 2], attribute_match=True
    )
    head = CellGroundingHead(16, cfg, grid_side=2).eval()
    hidden, key_mask = torch.randn(2, 7, 16), torch.ones(2, 7, dtype=torch.bool)
    inputs = (hidden, key_mask, torch.tensor([[1, 2, 3, 4]] * 2), torch.tensor([6, 5]))
    with torch.no_grad():
        head.attribute_match_weight.zero_()
        plain = head(*inputs)
        head.attribute_match_weight.copy_(torch.tensor([1.0, 0.5, 0.0, 2.0]))
        matched = head(*inputs)
    expected = attribute_match(
        matched.query_attributes, matched.cell_attributes, cfg.attribute_classes, head.attribute_match_weight
    )
    torch.testing.assert_close(matched.cell_logits - plain.cell_logits, expected)
    assert not torch.allclose(matched.cell_logits, plain.cell_logits)
