"""The grounding head's attribute loss and attribute match (model/grounding/head.py), checked by hand on tiny logits."""

from __future__ import annotations

import math

import pytest
import torch

from openfly_agent.model.config import BoxGroundingConfig, CellGroundingConfig
from openfly_agent.model.grounding.head import GroundingOutput, attribute_loss, grounding_loss

CFG = CellGroundingConfig(dim=8, num_heads=2, attribute_weight=2.0, attribute_classes=[2, 2, 2, 2])


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
        CellGroundingConfig(attribute_weight=-1.0)
    with pytest.raises(ValueError, match="attribute_classes"):
        CellGroundingConfig(attribute_classes=[12, 6, 3])
    with pytest.raises(TypeError, match="attribute_weight"):  # the box head has no attribute classifiers
        BoxGroundingConfig(attribute_weight=1.0)
