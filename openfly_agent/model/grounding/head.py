"""Landmark grounding (paper: landmark grounding): the two heads, the factory that picks one, and their loss.

Learned queries cross-attend (3 layers) to the LLM's last hidden states over the image and text positions
(model/grounding/layers.py) and give the instruction landmark's box `(cx, cy, w, h)` in [0, 1] in the current
frame, plus a visibility logit (our addition: at inference an invisible landmark has no box, so no keyframe area).
`grounding.type` picks the head: `box`, `BoxRegressionHead`, the paper's box regressed from the pooled queries
(every 7B preset); `cells`, `CellGroundingHead` (model/grounding/cells.py, the tiny preset), which scores every cell
of the frame's token grid and places the box centre from those scores; `none`, no head. Each variant registers its
builder here (model/config_choice.py). The loss is GIoU + L1 with a visibility
mask (+ the cell head's cell and attribute terms).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from openfly_agent.model.grounding.cells import CellGroundingHead
from openfly_agent.model.grounding.config import (
    BoxGroundingConfig,
    CellGroundingConfig,
    GroundingConfig,
    GroundingHeadConfig,
    NoGroundingConfig,
)
from openfly_agent.model.grounding.layers import GroundingOutput, QueryReader


class BoxRegressionHead(QueryReader):
    """The paper's head (`grounding.type: box`): an MLP regresses the box from the pooled queries.

    Args:
        llm_dim: LLM hidden size.
        cfg: grounding section of the model config.
    """

    def __init__(self, llm_dim: int, cfg: GroundingHeadConfig) -> None:
        super().__init__(llm_dim, cfg)
        self.box_mlp = nn.Sequential(nn.Linear(cfg.dim, cfg.dim), nn.GELU(), nn.Linear(cfg.dim, 4))

    def forward(
        self,
        hidden: torch.Tensor,
        key_mask: torch.Tensor,
        image_positions: torch.Tensor | None = None,
        last_positions: torch.Tensor | None = None,
        visual_cells: torch.Tensor | None = None,
    ) -> GroundingOutput:
        """Predict one box per sequence from hidden (B, L, D_llm) over key_mask (B, L) bool (the positions the head
        may read: image + prompt, never padding or targets). The frame's positions, the last prompt token and the
        visual cells, which the cell head reads, are accepted and unused: both heads take the agent's call."""
        reading = self.read(hidden, key_mask)
        return GroundingOutput(torch.sigmoid(self.box_mlp(reading.pooled)), reading.visibility)


GroundingHead = BoxRegressionHead | CellGroundingHead


def make_grounding_head(llm_dim: int, cfg: GroundingConfig, grid_side: int) -> GroundingHead | None:
    """The head `cfg.type` names, as its variant registered it: `CellGroundingHead` on the frame's grid_side x
    grid_side token grid (`cells`), the paper's `BoxRegressionHead` (`box`), or None (`none`)."""
    return cfg.build(llm_dim, grid_side)


@CellGroundingConfig.register_builder
def _cell_head(cfg: CellGroundingConfig, llm_dim: int, grid_side: int) -> CellGroundingHead:
    return CellGroundingHead(llm_dim, cfg, grid_side)


@BoxGroundingConfig.register_builder
def _box_head(cfg: BoxGroundingConfig, llm_dim: int, grid_side: int) -> BoxRegressionHead:
    return BoxRegressionHead(llm_dim, cfg)  # reads the pooled queries, not the grid


@NoGroundingConfig.register_builder
def _no_head(cfg: NoGroundingConfig, llm_dim: int, grid_side: int) -> None:
    return None


def cxcywh_to_xyxy(boxes: torch.Tensor) -> torch.Tensor:
    """(..., 4) centre/size -> corners."""
    cx, cy, w, h = boxes.unbind(-1)
    return torch.stack([cx - w / 2, cy - h / 2, cx + w / 2, cy + h / 2], dim=-1)


def iou_and_giou(pred: torch.Tensor, target: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Element-wise IoU and generalised IoU of (N, 4) cxcywh box pairs -> (N,), (N,)."""
    p, t = cxcywh_to_xyxy(pred.float()), cxcywh_to_xyxy(target.float())
    area_p = (p[:, 2] - p[:, 0]).clamp(min=0) * (p[:, 3] - p[:, 1]).clamp(min=0)
    area_t = (t[:, 2] - t[:, 0]).clamp(min=0) * (t[:, 3] - t[:, 1]).clamp(min=0)
    inter_wh = (torch.min(p[:, 2:], t[:, 2:]) - torch.max(p[:, :2], t[:, :2])).clamp(min=0)  # (N, 2)
    inter = inter_wh[:, 0] * inter_wh[:, 1]
    union = area_p + area_t - inter
    iou = inter / union.clamp(min=1e-9)
    hull_wh = (torch.max(p[:, 2:], t[:, 2:]) - torch.min(p[:, :2], t[:, :2])).clamp(min=0)
    hull = hull_wh[:, 0] * hull_wh[:, 1]
    return iou, iou - (hull - union) / hull.clamp(min=1e-9)


def box_cells(boxes: torch.Tensor, grid_side: int) -> torch.Tensor:
    """(..., 4) cxcywh -> (...) index of the cell holding each box centre (row-major on a grid_side grid)."""
    col = (boxes[..., 0] * grid_side).long().clamp(0, grid_side - 1)
    row = (boxes[..., 1] * grid_side).long().clamp(0, grid_side - 1)
    return row * grid_side + col


def grounding_loss(
    output: GroundingOutput,
    target_boxes: torch.Tensor,
    visible: torch.Tensor,
    cfg: GroundingHeadConfig,
    attributes: torch.Tensor | None = None,
) -> tuple[torch.Tensor, dict[str, float]]:
    """GIoU + l1_weight * L1 on visible boxes (mean), + visibility_weight * BCE on every sample, + cell_weight *
    cross-entropy of the cell holding the box centre (visible boxes, when the head scores cells), +
    attribute_weight * `attribute_loss` (when the head classifies attributes and the batch has them).

    Args:
        output: the head's prediction (boxes (B, 4) cxcywh, visibility logits (B,), cell logits (B, P) or None).
        target_boxes: (B, 4) ground truth cxcywh (ignored where not visible).
        visible: (B,) bool ground-truth visibility mask.
        cfg: grounding config (weights).
        attributes: (B, 4) long target attribute ids, -1 where unknown (None: no attribute term).

    Returns:
        The scalar loss and float logs: `box_iou` (mean IoU over visible boxes, 0 when none),
        `num_visible_boxes`, `giou_loss`, `l1_loss`, `visibility_loss`, `cell_loss` (and `attribute_loss`,
        `query_color_accuracy`, `cell_color_accuracy` with the attribute term).
    """
    pred_boxes, visibility_logits = output.boxes, output.visibility
    visible = visible.bool()
    count = int(visible.sum())
    zero = pred_boxes.sum() * 0.0  # keeps the graph when no box is visible
    cell_term = zero
    if count:
        target = target_boxes[visible].to(pred_boxes.device)
        iou, giou = iou_and_giou(pred_boxes[visible], target)
        giou_term = (1.0 - giou).mean()
        l1_term = F.l1_loss(pred_boxes[visible].float(), target.float(), reduction="none")
        l1_term = l1_term.sum(-1).mean()
        if output.cell_logits is not None:
            side = int(round(output.cell_logits.shape[-1] ** 0.5))
            cell_term = F.cross_entropy(output.cell_logits[visible].float(), box_cells(target, side))
    else:
        iou, giou_term, l1_term = torch.zeros(1), zero, zero
    vis_term = F.binary_cross_entropy_with_logits(visibility_logits.float(), visible.float())
    loss = giou_term + cfg.l1_weight * l1_term + cfg.visibility_weight * vis_term
    if output.cell_logits is not None:  # the cell head: its config has the weight
        loss = loss + cfg.cell_weight * cell_term
    attribute_logs = {}
    if output.query_attributes is not None and attributes is not None:
        attribute_term, attribute_logs = attribute_loss(output, target_boxes, visible, attributes, cfg)
        loss = loss + cfg.attribute_weight * attribute_term
    logs = {
        "box_iou": float(iou.detach().mean()) if count else 0.0,
        "num_visible_boxes": float(count),
        "giou_loss": float(giou_term.detach()),
        "l1_loss": float(l1_term.detach()),
        "visibility_loss": float(vis_term.detach()),
        "cell_loss": float(cell_term.detach()),
        **attribute_logs,
    }
    return loss, logs


def attribute_loss(
    output: GroundingOutput,
    target_boxes: torch.Tensor,
    visible: torch.Tensor,
    attributes: torch.Tensor,
    cfg: CellGroundingConfig,
) -> tuple[torch.Tensor, dict[str, float]]:
    """Mean cross-entropy of each attribute (colour, type, size, feature) of the target, from the query on every
    row and from the token cell holding the target's centre on rows where it is visible (-1 ids are skipped).

    Returns the loss and logs: `attribute_loss` and the colour accuracies `query_color_accuracy` and
    `cell_color_accuracy` (each absent when no row has a known colour to read)."""
    attributes = attributes.to(output.query_attributes.device).long()  # (B, 4)
    side = int(round(output.cell_attributes.shape[1] ** 0.5))  # the token grid
    rows = torch.nonzero(visible.to(attributes.device), as_tuple=True)[0]  # (V,)
    cells = box_cells(target_boxes[rows].to(output.cell_attributes.device).float(), side)  # (V,)
    at_target = output.cell_attributes[rows, cells]  # (V, A)
    terms, logs, first = [], {}, 0
    for k, count in enumerate(cfg.attribute_classes):
        for name, logits, labels in (
            ("query", output.query_attributes, attributes[:, k]),
            ("cell", at_target, attributes[rows, k]),
        ):
            known = labels >= 0
            if not bool(known.any()):
                continue
            part = logits[known, first : first + count].float()  # (n, count)
            terms.append(F.cross_entropy(part, labels[known]))
            if k == 0:
                accuracy = (part.argmax(dim=-1) == labels[known]).float().mean()
                logs[f"{name}_color_accuracy"] = float(accuracy)
        first += count
    # both classifiers stay in the graph when a batch gives one of them nothing to read (DDP needs every gradient)
    term = (output.query_attributes.sum() + output.cell_attributes.sum()) * 0.0
    if terms:
        term = term + torch.stack(terms).mean()
    logs["attribute_loss"] = float(term.detach())
    return term, logs
