"""The cell grounding head (`grounding.type: cells`, the tiny preset): per-cell scoring of the current frame.

The query starts from the hidden state of the last prompt token (it has read the whole instruction), its code
scales and shifts each cell's features (FiLM), an MLP gives one logit per cell, and the box centre is the
softmax-weighted cell centre plus a bounded offset; a cross-entropy over which cell holds the box centre joins the
loss (`cell_weight`). Dense, per-cell supervision learns much faster than one regressed box (docs/experiments/2026-11-23-agent-that-navigates-issue12.md,
"Grounding"). With `centre_window` = w, at inference (eval mode), the softmax that places the centre
(and pools the size's context) is renormalised over the (2w + 1) x (2w + 1) cells around the best-scoring cell, so
a score with two peaks picks one instead of averaging them; training keeps the softmax over every cell (trained
with the window, the head grounded no better). With `attribute_weight` the head also names the target's
attributes from its query and from every cell (`attribute_loss` in model/grounding/head.py). In a causal LLM
the frame's tokens precede the prompt, so a cell's features never see the instruction: the query's FiLM code
binds the two. With `visual_skip` each cell also gets a projection of the frame's visual token at its position
(the LLM's input there), so what the LLM's layers mix away still reaches the scorer.
"""

from __future__ import annotations

import torch
from torch import nn

from openfly_agent.model.grounding.config import CellGroundingConfig
from openfly_agent.model.grounding.layers import GroundingOutput, QueryReader


class CellScorer(nn.Module):
    """FiLM cell scoring: the query's code scales and shifts every cell's features, an MLP gives its logit."""

    def __init__(self, dim: int) -> None:
        super().__init__()
        self.norm = nn.LayerNorm(dim)
        self.scale, self.shift = nn.Linear(dim, dim), nn.Linear(dim, dim)
        # no bias on the last layer: a constant added to every cell's logit changes neither the softmax nor the
        # cell cross-entropy, so its gradient is rounding noise that Adam would turn into lr-sized steps
        self.score = nn.Sequential(nn.GELU(), nn.Linear(dim, dim), nn.GELU(), nn.Linear(dim, 1, bias=False))

    def forward(self, cells: torch.Tensor, code: torch.Tensor) -> torch.Tensor:
        """cells (B, g * g, d), code (B, d) -> (B, g * g) logits, row-major."""
        modulated = self.norm(cells) * (1 + self.scale(code)[:, None]) + self.shift(code)[:, None]
        return self.score(modulated).squeeze(-1)  # (B, g * g)


class CellGroundingHead(QueryReader):
    """Per-cell scoring of the current frame's token grid; the box centre from the cells' softmax.

    Args:
        llm_dim: LLM hidden size.
        cfg: grounding section of the model config (`type: cells`).
        grid_side: cells per side of the current frame's token grid.
    """

    def __init__(self, llm_dim: int, cfg: CellGroundingConfig, grid_side: int) -> None:
        if not grid_side:
            raise ValueError("grounding.type=cells needs the frame's token grid side")
        super().__init__(llm_dim, cfg)
        self.grid_side = grid_side
        self.centre_window = cfg.centre_window
        self.text_query = nn.Linear(llm_dim, cfg.dim)  # the last prompt token starts the query
        self.visual_proj = nn.Linear(llm_dim, cfg.dim) if cfg.visual_skip else None
        self.cell_scorer = CellScorer(cfg.dim)
        self.box_mlp = nn.Sequential(nn.Linear(2 * cfg.dim, cfg.dim), nn.GELU(), nn.Linear(cfg.dim, 4))
        # the attributes of the target (colour, type, size, feature logits, concatenated) from the query and from
        # each cell: supervision that makes both sides represent what tells one landmark from another
        classes = sum(cfg.attribute_classes)
        self.query_attributes = nn.Linear(cfg.dim, classes) if cfg.attribute_weight else None
        self.cell_attributes = nn.Linear(cfg.dim, classes) if cfg.attribute_weight else None

    def forward(
        self,
        hidden: torch.Tensor,
        key_mask: torch.Tensor,
        image_positions: torch.Tensor,
        last_positions: torch.Tensor,
        visual_cells: torch.Tensor | None = None,
    ) -> GroundingOutput:
        """Predict one box per sequence.

        Args:
            hidden: (B, L, D_llm) last-layer LLM hidden states.
            key_mask: (B, L) bool, positions the head may read (image + prompt, never padding/targets).
            image_positions: (B, P) long, positions of the current frame's tokens.
            last_positions: (B,) long, position of each row's last prompt token.
            visual_cells: (B, P, D_llm) the current frame's visual tokens, the LLM's inputs at `image_positions`
                (needed with `visual_skip`).
        """
        rows = torch.arange(hidden.shape[0], device=hidden.device)
        last = hidden[rows, last_positions].to(self.text_query.weight.dtype)  # (B, D_llm)
        reading = self.read(hidden, key_mask, self.text_query(last))
        memory, pooled = reading.memory, reading.pooled  # (B, L, d), (B, d)
        cells = torch.gather(
            memory, 1, image_positions[..., None].expand(-1, -1, memory.shape[-1])
        )  # (B, P, d)
        if self.visual_proj is not None:
            if visual_cells is None:
                raise ValueError(
                    "grounding.visual_skip needs the current frame's visual tokens (visual_cells)"
                )
            cells = cells + self.visual_proj(visual_cells.to(self.visual_proj.weight.dtype))  # (B, P, d)
        cell_logits = self.cell_scorer(cells, pooled)  # (B, P)
        query_attributes = cell_attributes = None
        if self.query_attributes is not None:
            query_attributes, cell_attributes = self.query_attributes(pooled), self.cell_attributes(cells)
        window = None if self.training else self.centre_window  # a decoding rule: training reads every cell
        weights = windowed_softmax(cell_logits, self.grid_side, window)  # (B, P)
        context = (weights[..., None] * cells).sum(dim=1)  # (B, d)
        raw = self.box_mlp(torch.cat([pooled, context], dim=-1))  # (B, 4)
        centre = weights @ cell_centres(self.grid_side, weights.device, weights.dtype)  # (B, 2)
        cxcy = (centre + torch.tanh(raw[:, :2]) / self.grid_side).clamp(0.0, 1.0)
        boxes = torch.cat([cxcy, torch.sigmoid(raw[:, 2:])], dim=-1)
        return GroundingOutput(boxes, reading.visibility, cell_logits, query_attributes, cell_attributes)


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


def cell_centres(grid_side: int, device=None, dtype=torch.float32) -> torch.Tensor:
    """(P, 2) normalised (x, y) centres of a grid_side x grid_side grid's cells, row-major.

    Computed on each call rather than kept in a buffer: transformers builds models on the meta device when
    loading, and a non-persistent buffer would come back uninitialised.
    """
    ys, xs = torch.meshgrid(
        torch.arange(grid_side, device=device), torch.arange(grid_side, device=device), indexing="ij"
    )
    return (torch.stack([xs.flatten() + 0.5, ys.flatten() + 0.5], dim=-1) / grid_side).to(dtype)
