"""What both grounding heads share (model/grounding/head.py): the cross-attention layer, the prediction type and the
query reader, the learned queries that cross-attend to the LLM's hidden states.

`QueryReader` owns the layers both heads have and reads only its own attributes; the two heads
(`BoxRegressionHead`, `CellGroundingHead`) add theirs beside them. The layers sit at the top of each head, as the
single head of earlier versions had them, so checkpoints keep their state-dict keys (`grounding_head.input_proj.*`,
`grounding_head.box_queries`, `grounding_head.layers.*`, `grounding_head.norm.*`, `grounding_head.visibility.*`).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn
from transformers import initialization as init

from openfly_agent.model.grounding.config import GroundingHeadConfig


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
    """What a grounding head predicts for a batch."""

    boxes: torch.Tensor  # (B, 4) cxcywh in [0, 1]
    visibility: torch.Tensor  # (B,) logits
    cell_logits: torch.Tensor | None = None  # (B, P) one logit per cell of the current frame (cell head only)
    # with `attribute_weight`: attribute logits (A = sum of `attribute_classes`) from the query, (B, A), and of
    # every token cell, (B, P, A)
    query_attributes: torch.Tensor | None = None
    cell_attributes: torch.Tensor | None = None
    # with `colour_vocabulary`: (B, C) logits of the target's colour as the prompt's words name it, and (B, P) the
    # cells' colour match logits (a part of cell_logits)
    word_colours: torch.Tensor | None = None
    match_logits: torch.Tensor | None = None


@dataclass
class QueryReading:
    """What the query read: the projected sequence and its final state."""

    memory: torch.Tensor  # (B, L, d) the hidden states projected to the head's width
    pooled: torch.Tensor  # (B, d) the query after the layers, normalised
    visibility: torch.Tensor  # (B,) visibility logits of the query


class QueryReader(nn.Module):
    """One learned query cross-attends (`num_layers` layers) to the LLM's hidden states; a visibility logit.

    Args:
        llm_dim: LLM hidden size.
        cfg: grounding section of the model config.
    """

    def __init__(self, llm_dim: int, cfg: GroundingHeadConfig) -> None:
        super().__init__()
        self.input_proj = nn.Linear(llm_dim, cfg.dim)
        self.box_queries = nn.Parameter(torch.zeros(1, cfg.dim))  # (1, d): one target, one query
        self.layers = nn.ModuleList(
            [CrossAttentionLayer(cfg.dim, cfg.num_heads) for _ in range(cfg.num_layers)]
        )
        self.norm = nn.LayerNorm(cfg.dim)
        self.visibility = nn.Linear(cfg.dim, 1)

    def init_weights(self) -> None:
        """Fresh init of what the agent's generic init leaves alone (transformers' init functions skip tensors
        loaded from a checkpoint)."""
        init.normal_(self.box_queries, std=0.02)

    def read(
        self, hidden: torch.Tensor, key_mask: torch.Tensor, start: torch.Tensor | None = None
    ) -> QueryReading:
        """hidden (B, L, D_llm), key_mask (B, L) bool, start (B, d) added to every query (None: the learned
        queries alone) -> `QueryReading`."""
        memory = self.input_proj(hidden.to(self.input_proj.weight.dtype))  # (B, L, d)
        queries = self.box_queries[None].expand(hidden.shape[0], -1, -1)  # (B, 1, d)
        if start is not None:
            queries = queries + start[:, None]
        for layer in self.layers:
            queries = layer(queries, memory, key_mask)
        pooled = self.norm(queries)[:, 0]  # (B, d)
        return QueryReading(memory, pooled, self.visibility(pooled).squeeze(-1))
