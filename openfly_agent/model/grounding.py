"""Landmark grounding head (paper: landmark grounding) and its GIoU + L1 loss with a visibility mask.

Learned queries cross-attend (3 layers) to the LLM's last hidden states over the image and text positions
and regress the instruction landmark's box `(cx, cy, w, h)` in [0, 1] in the current frame, plus a
visibility logit (our addition: at inference an invisible landmark has no box, so no keyframe area).

With `cells` (the tiny preset) the head also scores every cell of the current frame's token grid: the
query starts from the hidden state of the last prompt token (it has read the whole instruction), its code
scales and shifts each cell's features (FiLM), an MLP gives one logit per cell, and the box centre is the
softmax-weighted cell centre plus a bounded offset; a cross-entropy over which cell holds the box centre
joins the loss (`cell_weight`). Dense, per-cell supervision learns much faster than one regressed box
(docs/experiments/2026-11-23-agent-that-navigates-issue12.md, "Grounding"). With `subcells` = s > 1 each cell's MLP gives s x s logits, one per
sub-cell: the softmax, the centre and the cross-entropy then live on a grid s times finer than the tokens (a
small far target covers a fraction of one 16 px cell at 128 px). With `centre_window` = w, at inference (eval
mode), the softmax that places the centre (and pools the size's context) is renormalised over the
(2w + 1) x (2w + 1) cells around the best-scoring cell, so a score with two peaks picks one instead of averaging
them; training keeps the softmax over every cell (trained with the window, the head grounded no better).
With `attribute_weight` the head also names the target's attributes from its query and from every cell
(`attribute_loss`); with `attribute_match` each cell's logit gains the agreement of the two (`attribute_match`),
so a cell whose colour the query names scores higher without the FiLM scorer having to discover the match.
With `cell_fusion_layers` = n > 0 each cell first cross-attends (n layers) to the same readable sequence as the
queries: in a causal LLM the frame's tokens precede the prompt, so without them a cell's features never see the
instruction and only the query's FiLM code binds the two. With `visual_skip` each cell also gets a projection of
the frame's visual token at its position (the LLM's input there), so what the LLM's layers mix away still reaches
the scorer.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn

from openfly_agent.constants import LANDMARK_ATTRIBUTES, LANDMARK_BOXES, TARGET_ATTRIBUTES

from .config import GroundingConfig
from .landmark_cells import box_cells, dense_attribute_loss


class CrossAttentionLayer(nn.Module):
    """Pre-norm cross-attention from queries to a key/value sequence, then an MLP, both residual."""

    def __init__(self, dim: int, num_heads: int) -> None:
        super().__init__()
        self.num_heads = num_heads
        self.norm_q = nn.LayerNorm(dim)
        self.norm_kv = nn.LayerNorm(dim)
        self.q_proj = nn.Linear(dim, dim)
        self.k_proj = nn.Linear(dim, dim)
        self.v_proj = nn.Linear(dim, dim)
        self.out_proj = nn.Linear(dim, dim)
        self.norm_mlp = nn.LayerNorm(dim)
        self.mlp = nn.Sequential(nn.Linear(dim, 4 * dim), nn.GELU(), nn.Linear(4 * dim, dim))

    def _heads(self, x: torch.Tensor) -> torch.Tensor:
        b, n, d = x.shape
        return x.view(b, n, self.num_heads, d // self.num_heads).transpose(1, 2)  # (B, h, n, d/h)

    def forward(self, queries: torch.Tensor, memory: torch.Tensor, key_mask: torch.Tensor) -> torch.Tensor:
        """queries (B, Q, d), memory (B, L, d), key_mask (B, L) bool (True = attend) -> (B, Q, d)."""
        kv = self.norm_kv(memory)
        q, k, v = (
            self._heads(self.q_proj(self.norm_q(queries))),
            self._heads(self.k_proj(kv)),
            self._heads(self.v_proj(kv)),
        )
        attn = F.scaled_dot_product_attention(q, k, v, attn_mask=key_mask[:, None, None, :])  # (B, h, Q, d/h)
        queries = queries + self.out_proj(attn.transpose(1, 2).reshape(queries.shape))
        return queries + self.mlp(self.norm_mlp(queries))


@dataclass
class GroundingOutput:
    """What the head predicts for a batch."""

    boxes: torch.Tensor  # (B, 4) cxcywh in [0, 1]
    visibility: torch.Tensor  # (B,) logits
    cell_logits: torch.Tensor | None = None  # (B, P) one logit per cell of the current frame (`cells` only)
    # with `attribute_weight`: attribute logits (A = sum of `attribute_classes`) from the query, (B, A), and of
    # every token cell, (B, P, A)
    query_attributes: torch.Tensor | None = None
    cell_attributes: torch.Tensor | None = None


class CellScorer(nn.Module):
    """FiLM cell scoring: the query's code scales and shifts every cell's features, an MLP gives its logit (one per
    sub-cell with `subcells` > 1, on the grid `subcells` times finer than the cells)."""

    def __init__(self, dim: int, grid_side: int, subcells: int = 1) -> None:
        super().__init__()
        self.grid_side, self.subcells = grid_side, subcells
        self.norm = nn.LayerNorm(dim)
        self.scale, self.shift = nn.Linear(dim, dim), nn.Linear(dim, dim)
        # no bias on the last layer: a constant added to every cell's logit changes neither the softmax nor the
        # cell cross-entropy, so its gradient is rounding noise that Adam would turn into lr-sized steps
        self.score = nn.Sequential(
            nn.GELU(), nn.Linear(dim, dim), nn.GELU(), nn.Linear(dim, subcells**2, bias=False)
        )

    def forward(self, cells: torch.Tensor, code: torch.Tensor) -> torch.Tensor:
        """cells (B, g * g, d), code (B, d) -> (B, (g * s) ** 2) logits on the fine grid, row-major."""
        modulated = self.norm(cells) * (1 + self.scale(code)[:, None]) + self.shift(code)[:, None]
        logits = self.score(modulated)  # (B, g * g, s * s)
        g, s = self.grid_side, self.subcells
        return logits.view(-1, g, g, s, s).permute(0, 1, 3, 2, 4).reshape(-1, (g * s) ** 2)


class GroundingHead(nn.Module):
    """Box regression from LLM hidden states through learned queries (+ per-cell scoring with `cells`).

    Args:
        llm_dim: LLM hidden size.
        cfg: grounding section of the model config.
        grid_side: cells per side of the current frame's token grid (needed with `cfg.cells`).
    """

    def __init__(self, llm_dim: int, cfg: GroundingConfig, grid_side: int | None = None) -> None:
        super().__init__()
        self.input_proj = nn.Linear(llm_dim, cfg.dim)
        self.box_queries = nn.Parameter(torch.zeros(cfg.num_queries, cfg.dim))
        self.layers = nn.ModuleList(
            [CrossAttentionLayer(cfg.dim, cfg.num_heads) for _ in range(cfg.num_layers)]
        )
        self.norm = nn.LayerNorm(cfg.dim)
        self.visibility = nn.Linear(cfg.dim, 1)
        self.cells = cfg.cells
        if not cfg.cells:
            self.box_mlp = nn.Sequential(nn.Linear(cfg.dim, cfg.dim), nn.GELU(), nn.Linear(cfg.dim, 4))
            return
        if not grid_side:
            raise ValueError("grounding.cells needs the frame's token grid side")
        self.grid_side, self.fine_side = grid_side, grid_side * cfg.subcells
        self.centre_window = cfg.centre_window
        self.text_query = nn.Linear(llm_dim, cfg.dim)  # the last prompt token starts the query
        self.visual_proj = nn.Linear(llm_dim, cfg.dim) if cfg.visual_skip else None
        self.cell_layers = nn.ModuleList(
            [CrossAttentionLayer(cfg.dim, cfg.num_heads) for _ in range(cfg.cell_fusion_layers)]
        )
        self.cell_scorer = CellScorer(cfg.dim, grid_side, cfg.subcells)
        self.box_mlp = nn.Sequential(nn.Linear(2 * cfg.dim, cfg.dim), nn.GELU(), nn.Linear(cfg.dim, 4))
        # the attributes of the target (colour, type, size, feature logits, concatenated) from the query and from
        # each cell: supervision that makes both sides represent what tells one landmark from another
        classes = sum(cfg.attribute_classes)
        self.query_attributes = nn.Linear(cfg.dim, classes) if cfg.attribute_weight else None
        self.cell_attributes = nn.Linear(cfg.dim, classes) if cfg.attribute_weight else None
        self.attribute_classes = list(cfg.attribute_classes)
        # with `attribute_match`: one learned weight per attribute of the cells' attribute agreement with the query
        self.attribute_match_weight = (
            nn.Parameter(torch.ones(len(cfg.attribute_classes))) if cfg.attribute_match else None
        )

    def forward(
        self,
        hidden: torch.Tensor,
        key_mask: torch.Tensor,
        image_positions: torch.Tensor | None = None,
        last_positions: torch.Tensor | None = None,
        visual_cells: torch.Tensor | None = None,
    ) -> GroundingOutput:
        """Predict one box per sequence.

        Args:
            hidden: (B, L, D_llm) last-layer LLM hidden states.
            key_mask: (B, L) bool, positions the head may read (image + prompt, never padding/targets).
            image_positions: (B, P) long, positions of the current frame's tokens (`cells` only).
            last_positions: (B,) long, position of each row's last prompt token (`cells` only).
            visual_cells: (B, P, D_llm) the current frame's visual tokens, the LLM's inputs at `image_positions`
                (needed with `visual_skip`).
        """
        memory = self.input_proj(hidden.to(self.input_proj.weight.dtype))  # (B, L, d)
        batch = hidden.shape[0]
        queries = self.box_queries[None].expand(batch, -1, -1)  # (B, Q, d)
        if self.cells:
            rows = torch.arange(batch, device=hidden.device)
            last = hidden[rows, last_positions].to(self.text_query.weight.dtype)  # (B, D_llm)
            queries = queries + self.text_query(last)[:, None]
        for layer in self.layers:
            queries = layer(queries, memory, key_mask)
        pooled = self.norm(queries).mean(dim=1)  # (B, d)
        visibility = self.visibility(pooled).squeeze(-1)  # (B,)
        if not self.cells:
            return GroundingOutput(torch.sigmoid(self.box_mlp(pooled)), visibility)
        cells = torch.gather(
            memory, 1, image_positions[..., None].expand(-1, -1, memory.shape[-1])
        )  # (B, P, d)
        if self.visual_proj is not None:
            if visual_cells is None:
                raise ValueError(
                    "grounding.visual_skip needs the current frame's visual tokens (visual_cells)"
                )
            cells = cells + self.visual_proj(visual_cells.to(self.visual_proj.weight.dtype))  # (B, P, d)
        for layer in self.cell_layers:
            cells = layer(cells, memory, key_mask)  # (B, P, d): each cell reads the prompt (and the frame)
        cell_logits = self.cell_scorer(cells, pooled)  # (B, F), F = (g * s)^2 fine cells
        query_attributes = cell_attributes = None
        if self.query_attributes is not None:
            query_attributes, cell_attributes = self.query_attributes(pooled), self.cell_attributes(cells)
        if self.attribute_match_weight is not None:
            match = attribute_match(
                query_attributes, cell_attributes, self.attribute_classes, self.attribute_match_weight
            )  # (B, P)
            cell_logits = cell_logits + fine_grid(match, self.grid_side, self.fine_side // self.grid_side)
        window = None if self.training else self.centre_window  # a decoding rule: training reads every cell
        weights = windowed_softmax(cell_logits, self.fine_side, window)  # (B, F)
        context = (coarse_weights(weights, self.grid_side)[..., None] * cells).sum(dim=1)  # (B, d)
        raw = self.box_mlp(torch.cat([pooled, context], dim=-1))  # (B, 4)
        centre = weights @ cell_centres(self.fine_side, weights.device, weights.dtype)  # (B, 2)
        cxcy = (centre + torch.tanh(raw[:, :2]) / self.fine_side).clamp(0.0, 1.0)
        boxes = torch.cat([cxcy, torch.sigmoid(raw[:, 2:])], dim=-1)
        return GroundingOutput(boxes, visibility, cell_logits, query_attributes, cell_attributes)


def attribute_match(
    query_logits: torch.Tensor, cell_logits: torch.Tensor, classes: list[int], weights: torch.Tensor
) -> torch.Tensor:
    """How well each cell's attributes agree with the query's: sum over attributes k of weights[k] x the expected
    log-probability, under the cell's distribution of attribute k, of the class the query names (its softmax).

    query_logits (B, A), cell_logits (B, P, A), A = sum(classes) -> (B, P), <= 0 for non-negative weights.
    """
    match, first = 0.0, 0
    for k, count in enumerate(classes):
        query = query_logits[:, first : first + count].float().softmax(dim=-1)  # (B, C)
        cell = cell_logits[..., first : first + count].float().log_softmax(dim=-1)  # (B, P, C)
        match = match + weights[k] * (cell * query[:, None]).sum(dim=-1)
        first += count
    return match


def fine_grid(per_cell: torch.Tensor, grid_side: int, subcells: int) -> torch.Tensor:
    """(B, g * g) row-major values per token cell -> (B, (g * s) ** 2), each sub-cell its cell's value."""
    if subcells == 1:
        return per_cell
    grid = per_cell.view(-1, grid_side, grid_side)
    grid = grid.repeat_interleave(subcells, dim=1).repeat_interleave(subcells, dim=2)
    return grid.reshape(per_cell.shape[0], -1)


def windowed_softmax(logits: torch.Tensor, grid_side: int, window: int | None) -> torch.Tensor:
    """(B, g * g) row-major cell logits -> (B, g * g) softmax over the (2w + 1) x (2w + 1) cells around each row's
    argmax (zero elsewhere; clipped at the grid's edge), or over every cell when `window` is None."""
    if window is None:
        return logits.softmax(dim=-1)
    best = logits.argmax(dim=-1)  # (B,)
    index = torch.arange(grid_side * grid_side, device=logits.device)  # (F,)
    row_gap = (index[None] // grid_side - (best // grid_side)[:, None]).abs()  # (B, F)
    col_gap = (index[None] % grid_side - (best % grid_side)[:, None]).abs()  # (B, F)
    inside = (row_gap <= window) & (col_gap <= window)
    return logits.masked_fill(~inside, float("-inf")).softmax(dim=-1)


def coarse_weights(fine: torch.Tensor, grid_side: int) -> torch.Tensor:
    """(B, (g * s)^2) weights on a fine row-major grid -> (B, g * g), each cell the sum of its s x s sub-cells."""
    s = int(round((fine.shape[-1] ** 0.5) / grid_side))
    return fine.view(-1, grid_side, s, grid_side, s).sum(dim=(2, 4)).reshape(-1, grid_side**2)


def cell_centres(grid_side: int, device=None, dtype=torch.float32) -> torch.Tensor:
    """(P, 2) normalised (x, y) centres of a grid_side x grid_side grid's cells, row-major.

    Computed on each call rather than kept in a buffer: transformers builds models on the meta device when
    loading, and a non-persistent buffer would come back uninitialised.
    """
    ys, xs = torch.meshgrid(
        torch.arange(grid_side, device=device), torch.arange(grid_side, device=device), indexing="ij"
    )
    return (torch.stack([xs.flatten() + 0.5, ys.flatten() + 0.5], dim=-1) / grid_side).to(dtype)


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


def grounding_labels(
    batch: Mapping,
) -> tuple[torch.Tensor | None, tuple[torch.Tensor, torch.Tensor] | None]:
    """A batch's labels for `grounding_loss` beyond the box: (target attribute ids (B, 4) or None, (landmark
    boxes (B, M, 4), landmark attribute ids (B, M, 4)) or None)."""
    landmarks = None
    if LANDMARK_BOXES in batch:
        landmarks = (batch[LANDMARK_BOXES], batch[LANDMARK_ATTRIBUTES])
    return batch.get(TARGET_ATTRIBUTES), landmarks


def grounding_loss(
    output: GroundingOutput,
    target_boxes: torch.Tensor,
    visible: torch.Tensor,
    cfg: GroundingConfig,
    attributes: torch.Tensor | None = None,
    landmarks: tuple[torch.Tensor, torch.Tensor] | None = None,
) -> tuple[torch.Tensor, dict[str, float]]:
    """GIoU + l1_weight * L1 on visible boxes (mean), + visibility_weight * BCE on every sample, + cell_weight *
    cross-entropy of the cell holding the box centre (visible boxes, when the head scores cells), +
    attribute_weight * `attribute_loss` (when the head classifies attributes and the batch has them), +
    dense_attribute_weight * `dense_attribute_loss` of every labelled cell (when the batch has `landmarks`).

    Args:
        output: the head's prediction (boxes (B, 4) cxcywh, visibility logits (B,), cell logits (B, P) or None).
        target_boxes: (B, 4) ground truth cxcywh (ignored where not visible).
        visible: (B,) bool ground-truth visibility mask.
        cfg: grounding config (weights).
        attributes: (B, 4) long target attribute ids, -1 where unknown (None: no attribute term).
        landmarks: (boxes (B, M, 4), attribute ids (B, M, 4)) of every landmark of each row's frame
            (model/landmark_cells.py; None: no dense term).

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
    loss = (
        giou_term + cfg.l1_weight * l1_term + cfg.visibility_weight * vis_term + cfg.cell_weight * cell_term
    )
    attribute_logs = {}
    if output.query_attributes is not None and attributes is not None:
        attribute_term, attribute_logs = attribute_loss(output, target_boxes, visible, attributes, cfg)
        loss = loss + cfg.attribute_weight * attribute_term
    if output.cell_attributes is not None and cfg.dense_attribute_weight and landmarks is not None:
        dense_term, dense_logs = dense_attribute_loss(
            output.cell_attributes, *landmarks, cfg.attribute_classes
        )
        loss = loss + cfg.dense_attribute_weight * dense_term
        attribute_logs.update(dense_logs)
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
    cfg: GroundingConfig,
) -> tuple[torch.Tensor, dict[str, float]]:
    """Mean cross-entropy of each attribute (colour, type, size, feature) of the target, from the query on every
    row and from the token cell holding the target's centre on rows where it is visible (-1 ids are skipped).

    Returns the loss and logs: `attribute_loss` and the colour accuracies `query_color_accuracy` and
    `cell_color_accuracy` (each absent when no row has a known colour to read)."""
    attributes = attributes.to(output.query_attributes.device).long()  # (B, 4)
    side = int(round(output.cell_attributes.shape[1] ** 0.5))  # the token grid (sub-cells are not classified)
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
