"""Landmark grounding head (paper: landmark grounding) and its GIoU + L1 loss with a visibility mask.

Learned queries cross-attend (3 layers) to the LLM's last hidden states over the image and text positions
and regress the instruction landmark's box `(cx, cy, w, h)` in [0, 1] in the current frame, plus a
visibility logit (our addition: at inference an invisible landmark has no box, so no keyframe area).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from .config import GroundingConfig


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


class GroundingHead(nn.Module):
    """Box regression from LLM hidden states through learned queries.

    Args:
        llm_dim: LLM hidden size.
        cfg: grounding section of the model config.
    """

    def __init__(self, llm_dim: int, cfg: GroundingConfig) -> None:
        super().__init__()
        self.input_proj = nn.Linear(llm_dim, cfg.dim)
        self.box_queries = nn.Parameter(torch.zeros(cfg.num_queries, cfg.dim))
        self.layers = nn.ModuleList(
            [CrossAttentionLayer(cfg.dim, cfg.num_heads) for _ in range(cfg.num_layers)]
        )
        self.norm = nn.LayerNorm(cfg.dim)
        self.box_mlp = nn.Sequential(nn.Linear(cfg.dim, cfg.dim), nn.GELU(), nn.Linear(cfg.dim, 4))
        self.visibility = nn.Linear(cfg.dim, 1)

    def forward(self, hidden: torch.Tensor, key_mask: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Predict one box per sequence.

        Args:
            hidden: (B, L, D_llm) last-layer LLM hidden states.
            key_mask: (B, L) bool, positions the head may read (image + prompt, never padding/targets).

        Returns:
            (B, 4) boxes (cx, cy, w, h) in (0, 1) and (B,) visibility logits.
        """
        memory = self.input_proj(hidden.to(self.input_proj.weight.dtype))  # (B, L, d)
        queries = self.box_queries[None].expand(hidden.shape[0], -1, -1)  # (B, Q, d)
        for layer in self.layers:
            queries = layer(queries, memory, key_mask)
        pooled = self.norm(queries).mean(dim=1)  # (B, d)
        return torch.sigmoid(self.box_mlp(pooled)), self.visibility(pooled).squeeze(-1)


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


def grounding_loss(
    pred_boxes: torch.Tensor,
    visibility_logits: torch.Tensor,
    target_boxes: torch.Tensor,
    visible: torch.Tensor,
    cfg: GroundingConfig,
) -> tuple[torch.Tensor, dict[str, float]]:
    """GIoU + l1_weight * L1 on visible boxes (mean), + visibility_weight * BCE on every sample.

    Args:
        pred_boxes: (B, 4) predicted cxcywh.
        visibility_logits: (B,) predicted visibility logits.
        target_boxes: (B, 4) ground truth cxcywh (ignored where not visible).
        visible: (B,) bool ground-truth visibility mask.
        cfg: grounding config (weights).

    Returns:
        The scalar loss and float logs: `box_iou` (mean IoU over visible boxes, 0 when none),
        `num_visible_boxes`, `giou_loss`, `l1_loss`, `visibility_loss`.
    """
    visible = visible.bool()
    count = int(visible.sum())
    zero = pred_boxes.sum() * 0.0  # keeps the graph when no box is visible
    if count:
        iou, giou = iou_and_giou(pred_boxes[visible], target_boxes[visible].to(pred_boxes.device))
        giou_term = (1.0 - giou).mean()
        l1_term = F.l1_loss(pred_boxes[visible].float(), target_boxes[visible].float(), reduction="none")
        l1_term = l1_term.sum(-1).mean()
    else:
        iou, giou_term, l1_term = torch.zeros(1), zero, zero
    vis_term = F.binary_cross_entropy_with_logits(visibility_logits.float(), visible.float())
    loss = giou_term + cfg.l1_weight * l1_term + cfg.visibility_weight * vis_term
    logs = {
        "box_iou": float(iou.detach().mean()) if count else 0.0,
        "num_visible_boxes": float(count),
        "giou_loss": float(giou_term.detach()),
        "l1_loss": float(l1_term.detach()),
        "visibility_loss": float(vis_term.detach()),
    }
    return loss, logs
