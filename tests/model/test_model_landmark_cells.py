"""Dense attribute labels (model/grounding/landmark_cells.py): each cell named by the smallest landmark it shows, checked by
hand on a 4 x 4 grid, and their loss inside `grounding_loss`."""

from __future__ import annotations

import pytest
import torch
import torch.nn.functional as F

from openfly_agent.model.config import GroundingConfig
from openfly_agent.model.grounding.head import GroundingOutput, grounding_loss
from openfly_agent.model.grounding.landmark_cells import dense_attribute_loss, landmark_cell_labels

# a 4 x 4 grid: cell centres at 0.125, 0.375, 0.625, 0.875 on each axis
WIDE = [0.5, 0.5, 1.0, 0.5]  # holds the centres of rows 1 and 2 (y 0.375, 0.625), every column
SMALL = [0.3, 0.6, 0.05, 0.05]  # holds no cell centre; its own centre lies in row 2, column 1: cell 9
TALL = [0.875, 0.5, 0.1, 1.0]  # holds the centres of column 3, every row; smaller than WIDE (0.1 vs 0.5)
PAD = [0.0, 0.0, 0.0, 0.0]


def _labels(boxes, ids):
    return landmark_cell_labels(torch.tensor([boxes]), torch.tensor([ids]), 4)[0]  # (16, 4)


def test_each_cell_takes_the_smallest_landmark_it_shows():
    labels = _labels([WIDE, SMALL, TALL, PAD], [[1, 1, 1, 1], [2, 2, 2, 2], [3, 3, 3, 3], [-1] * 4])
    expected = [-1, -1, -1, 3, 1, 1, 1, 3, 1, 2, 1, 3, -1, -1, -1, 3]  # row-major
    assert labels[:, 0].tolist() == expected
    assert (labels == labels[:, :1]).all()  # every attribute from the same landmark


def test_order_of_the_landmarks_does_not_matter_and_padding_labels_nothing():
    forward = _labels([WIDE, SMALL, TALL], [[1, 0, 0, 0], [2, 0, 0, 0], [3, 0, 0, 0]])
    backward = _labels([TALL, SMALL, WIDE], [[3, 0, 0, 0], [2, 0, 0, 0], [1, 0, 0, 0]])
    assert torch.equal(forward, backward)
    assert (_labels([PAD, PAD], [[5, 5, 5, 5], [6, 6, 6, 6]]) == -1).all()


def test_an_unknown_attribute_of_the_smallest_landmark_stays_unknown():
    labels = _labels([WIDE, SMALL], [[1, 1, 1, 1], [2, -1, 2, 2]])
    assert labels[9].tolist() == [2, -1, 2, 2]  # not the wide landmark's type: the cell shows the small one


def test_dense_loss_by_hand():
    classes = [2, 3, 2, 2]
    logits = torch.randn(1, 16, sum(classes), generator=torch.Generator().manual_seed(0))
    boxes, ids = torch.tensor([[WIDE, SMALL]]), torch.tensor([[[1, 2, 0, -1], [0, 0, 1, -1]]])
    term, logs = dense_attribute_loss(logits, boxes, ids, classes)
    labelled = [4, 5, 6, 7, 8, 9, 10, 11]  # rows 1 and 2; cell 9 the small landmark's
    per_cell = {cell: ids[0, 1] if cell == 9 else ids[0, 0] for cell in labelled}
    expected, first = [], 0
    for k, count in enumerate(classes[:3]):  # the feature is unknown everywhere: no term
        rows = torch.stack([logits[0, cell, first : first + count] for cell in labelled])
        expected.append(F.cross_entropy(rows, torch.stack([per_cell[cell][k] for cell in labelled])))
        first += count
    assert term.item() == pytest.approx(torch.stack(expected).mean().item(), rel=1e-5)
    assert logs["dense_labelled_cells"] == 8.0


def test_grounding_loss_adds_the_dense_term_only_with_its_weight_and_landmarks():
    cells = torch.randn(2, 16, 8, generator=torch.Generator().manual_seed(1))
    output = GroundingOutput(
        boxes=torch.full((2, 4), 0.5), visibility=torch.zeros(2), cell_logits=torch.zeros(2, 16),
        query_attributes=torch.zeros(2, 8), cell_attributes=cells,
    )  # fmt: skip
    boxes, visible = torch.tensor([[0.5, 0.5, 0.2, 0.2]] * 2), torch.tensor([True, True])
    landmarks = (torch.tensor([[WIDE], [PAD]]), torch.tensor([[[1, 0, 1, 0]], [[-1] * 4]]))
    off = GroundingConfig(dim=8, num_heads=2, attribute_weight=1.0, attribute_classes=[2, 2, 2, 2])
    on = GroundingConfig(**{**off.__dict__, "dense_attribute_weight": 3.0})
    base, base_logs = grounding_loss(output, boxes, visible, off, None, landmarks)
    full, logs = grounding_loss(output, boxes, visible, on, None, landmarks)
    term, _ = dense_attribute_loss(cells, *landmarks, [2, 2, 2, 2])
    assert "dense_attribute_loss" not in base_logs
    assert full.item() == pytest.approx(base.item() + 3.0 * term.item(), rel=1e-5)
    assert grounding_loss(output, boxes, visible, on)[0].item() == pytest.approx(base.item())


def test_dense_weight_needs_the_cell_classifiers():
    with pytest.raises(ValueError, match="dense_attribute_weight needs"):
        GroundingConfig(dense_attribute_weight=1.0)
    with pytest.raises(ValueError, match="dense_attribute_weight must be >= 0"):
        GroundingConfig(attribute_weight=1.0, dense_attribute_weight=-1.0)
