"""The cell grounding head (`grounding.cells: true`, the tiny preset): per-cell scoring of the current frame.

The query starts from the hidden state of the last prompt token (it has read the whole instruction), its code
scales and shifts each cell's features (FiLM), an MLP gives one logit per cell, and the box centre is the
softmax-weighted cell centre plus a bounded offset; a cross-entropy over which cell holds the box centre joins the
loss (`cell_weight`). Dense, per-cell supervision learns much faster than one regressed box (docs/experiments/2026-11-23-agent-that-navigates-issue12.md,
"Grounding"). With `subcells` = s > 1 each cell's MLP gives s x s logits, one per sub-cell: the softmax, the centre
and the cross-entropy then live on a grid s times finer than the tokens (a small far target covers a fraction of
one 16 px cell at 128 px). With `centre_window` = w, at inference (eval mode), the softmax that places the centre
(and pools the size's context) is renormalised over the (2w + 1) x (2w + 1) cells around the best-scoring cell, so
a score with two peaks picks one instead of averaging them; training keeps the softmax over every cell (trained
with the window, the head grounded no better). With `attribute_weight` the head also names the target's
attributes from its query and from every cell (`attribute_loss` in model/grounding/head.py); with `attribute_match`
each cell's logit gains the agreement of the two (`attribute_match`), so a cell whose colour the query names
scores higher without the FiLM scorer having to discover the match. With `cell_fusion_layers` = n > 0 each cell
first cross-attends (n layers) to the same readable sequence as the queries: in a causal LLM the frame's tokens
precede the prompt, so without them a cell's features never see the instruction and only the query's FiLM code
binds the two. With `visual_skip` each cell also gets a projection of the frame's visual token at its position
(the LLM's input there), so what the LLM's layers mix away still reaches the scorer.
"""

from __future__ import annotations

import torch
from torch import nn
from transformers import initialization as init

from openfly_agent.model.grounding.config import GroundingConfig
from openfly_agent.model.grounding.layers import CrossAttentionLayer, GroundingOutput, QueryReader


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


class CellGroundingHead(QueryReader):
    """Per-cell scoring of the current frame's token grid; the box centre from the cells' softmax.

    Args:
        llm_dim: LLM hidden size.
        cfg: grounding section of the model config (`cells: true`).
        grid_side: cells per side of the current frame's token grid.
    """

    def __init__(self, llm_dim: int, cfg: GroundingConfig, grid_side: int) -> None:
        if not grid_side:
            raise ValueError("grounding.cells needs the frame's token grid side")
        super().__init__(llm_dim, cfg)
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

    def init_weights(self) -> None:
        """The queries' init, and every attribute-match weight at 1."""
        super().init_weights()
        if self.attribute_match_weight is not None:
            init.ones_(self.attribute_match_weight)

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
        return GroundingOutput(boxes, reading.visibility, cell_logits, query_attributes, cell_attributes)


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
