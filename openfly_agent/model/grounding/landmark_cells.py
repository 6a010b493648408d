"""Dense attribute labels: every token cell of a frame named by the landmark it shows, and their loss.

The grounding stage's expression frames come with the box of every visible landmark (toolchain/grounding.py), and
an embedded city knows each landmark's colour, type, size and feature (training/attribute_targets.py). The target
cell alone gives the head's cell classifiers one label per sequence, mostly of landmarks that cover a fraction of
their cell; labelling every cell that shows a landmark gives about as many labels as the frame has landmarks
(`grounding.dense_attribute_weight`, docs/ARCHITECTURE.md).

Rule: a cell shows a landmark when the landmark's box holds the cell's centre or the cell holds the box's centre
(so a landmark smaller than a cell still labels one); where several do, the smallest box wins (it is the one the
cell's pixels single out; a large box often frames the sky and its neighbours too).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F


def box_cells(boxes: torch.Tensor, grid_side: int) -> torch.Tensor:
    """(..., 4) cxcywh -> (...) index of the cell holding each box centre (row-major on a grid_side grid)."""
    col = (boxes[..., 0] * grid_side).long().clamp(0, grid_side - 1)
    row = (boxes[..., 1] * grid_side).long().clamp(0, grid_side - 1)
    return row * grid_side + col


def landmark_cell_labels(boxes: torch.Tensor, attributes: torch.Tensor, side: int) -> torch.Tensor:
    """Each cell's attribute ids under the rule above.

    Args:
        boxes: (B, M, 4) cxcywh in [0, 1] of the landmarks of each row's frame; padding rows have w = h = 0.
        attributes: (B, M, 4) long ids (colour, type, size, feature), -1 where unknown.
        side: cells per side of the token grid.

    Returns:
        (B, side * side, 4) long, row-major cells, -1 where no landmark shows (or its attribute is unknown).
    """
    boxes = boxes.float()
    steps = (torch.arange(side, device=boxes.device, dtype=boxes.dtype) + 0.5) / side  # (g,)
    centre_y, centre_x = torch.meshgrid(steps, steps, indexing="ij")
    cell_x, cell_y = centre_x.reshape(1, 1, -1), centre_y.reshape(1, 1, -1)  # (1, 1, P)
    cx, cy, w, h = (boxes[..., k : k + 1] for k in range(4))  # (B, M, 1) each
    holds_cell_centre = ((cell_x - cx).abs() <= w / 2) & ((cell_y - cy).abs() <= h / 2)  # (B, M, P)
    holds_box_centre = box_cells(boxes, side)[..., None] == torch.arange(
        side * side, device=boxes.device
    )  # (B, M, P)
    real = (boxes[..., 2] > 0) & (boxes[..., 3] > 0)  # (B, M)
    shows = (holds_cell_centre | holds_box_centre) & real[..., None]  # (B, M, P)
    area = (boxes[..., 2] * boxes[..., 3])[..., None].expand_as(shows)  # (B, M, P)
    smallest = torch.where(shows, area, torch.full_like(area, float("inf"))).argmin(dim=1)  # (B, P)
    labels = torch.gather(
        attributes.long(), 1, smallest[..., None].expand(-1, -1, attributes.shape[-1])
    )  # (B, P, 4)
    return torch.where(shows.any(dim=1)[..., None], labels, torch.full_like(labels, -1))


def dense_attribute_loss(
    cell_attributes: torch.Tensor,
    boxes: torch.Tensor,
    attributes: torch.Tensor,
    classes: list[int],
) -> tuple[torch.Tensor, dict[str, float]]:
    """Mean over the attributes of the cross-entropy of every labelled cell's logits.

    Args:
        cell_attributes: (B, P, A) the head's per-cell attribute logits, A = sum(classes), in `classes`' order.
        boxes, attributes: the landmarks of each row's frame (`landmark_cell_labels`).
        classes: classes of each attribute.

    Returns:
        The loss (a zero that keeps the graph when no cell is labelled) and logs: `dense_attribute_loss`,
        `dense_labelled_cells` (labelled cells per row) and `dense_color_accuracy` (when a colour is labelled).
    """
    side = int(round(cell_attributes.shape[1] ** 0.5))
    labels = landmark_cell_labels(
        boxes.to(cell_attributes.device), attributes.to(cell_attributes.device), side
    )
    terms, logs, first = [], {}, 0
    for k, count in enumerate(classes):
        known = labels[..., k] >= 0  # (B, P)
        if bool(known.any()):
            logits = cell_attributes[..., first : first + count][known].float()  # (n, count)
            terms.append(F.cross_entropy(logits, labels[..., k][known]))
            if k == 0:
                logs["dense_color_accuracy"] = float(
                    (logits.argmax(-1) == labels[..., 0][known]).float().mean()
                )
        first += count
    term = cell_attributes.sum() * 0.0
    if terms:
        term = term + torch.stack(terms).mean()
    logs["dense_attribute_loss"] = float(term.detach())
    logs["dense_labelled_cells"] = float((labels >= 0).any(-1).sum(-1).float().mean())
    return term, logs
