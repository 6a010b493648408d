"""Landmark grounding (paper: landmark grounding): the two heads, the factory that picks one, and their loss.

Learned queries cross-attend (3 layers) to the LLM's last hidden states over the image and text positions
(model/grounding/layers.py) and give the instruction landmark's box `(cx, cy, w, h)` in [0, 1] in the current
frame, plus a visibility logit (our addition: at inference an invisible landmark has no box, so no keyframe area).
`grounding.type` picks the head: `box`, `BoxRegressionHead`, the paper's box regressed from the pooled queries
(every 7B preset); `cells`, `CellGroundingHead` (the tiny preset), which scores every cell of the frame's token grid
and places the box centre from those scores; `none`, no head. Each variant registers its builder here
(model/config_choice.py). The loss is GIoU + L1 with a visibility mask (+ the cell head's cell and attribute terms).

The cell head scores every cell of the current frame: its query starts from the hidden state of the last prompt
token (it has read the whole instruction), its code scales and shifts each cell's features (FiLM), an MLP gives
one logit per cell, and the box centre is the softmax-weighted cell centre plus a bounded offset; a cross-entropy
over which cell holds the box centre joins the loss (`cell_weight`). Dense, per-cell supervision learns much faster
than one regressed box (docs/experiments/2026-11-23-agent-that-navigates-issue12.md, "Grounding"). With
`centre_window` = w, at inference (eval mode), the softmax that places the centre (and pools the size's context)
is renormalised over the (2w + 1) x (2w + 1) cells around the best-scoring cell, so a score with two peaks picks
one instead of averaging them; training keeps the softmax over every cell (trained with the window, the head
grounded no better). With `attribute_weight` the head also names the target's attributes from its query and from
every cell (`attribute_loss`). In a causal LLM the frame's tokens precede the prompt, so a cell's features never
see the instruction: the query's FiLM code binds the two. With `visual_skip` each cell also gets a projection of
the frame's visual token at its position (the LLM's input there), so what the LLM's layers mix away still reaches
the scorer. With `colour_vocabulary` a reader of the prompt's words names the target's colour (trained on its
label), each pixel of the current frame is classed as one of the same named colours or none, and w x log(the
cell's share of the named colour) joins the cell's score (`ColourVocabulary`): the ResNet's stride-16 features
average away the colour of a landmark a few pixels wide, the share keeps it.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn
from transformers import initialization as init

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
        colours: torch.Tensor | None = None,
        words: torch.Tensor | None = None,
        word_mask: torch.Tensor | None = None,
    ) -> GroundingOutput:
        """Predict one box per sequence from hidden (B, L, D_llm) over key_mask (B, L) bool (the positions the head
        may read: image + prompt, never padding or targets). The frame's positions, the last prompt token, the
        visual cells, the cell colours and the prompt's words, which the cell head reads, are accepted and unused:
        both heads take the agent's call."""
        reading = self.read(hidden, key_mask)
        return GroundingOutput(torch.sigmoid(self.box_mlp(reading.pooled)), reading.visibility)


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


class ColourVocabulary(nn.Module):
    """A colour path from the pixels to the cell scores in the named colours' own vocabulary.

    - Words: a reader of the prompt's input embeddings names the target's colour, (B, C) logits over the C named
      colours. Each word gets a score from its embedding and its relative place in the prompt (the target is named
      last in an instruction), the scores' softmax pools the words, a linear layer names the colour. It is trained
      by the cross-entropy against the target's colour (`TARGET_ATTRIBUTES`, `word_colour_loss`), not through the
      cells: the LLM's query did not learn the colour word within the main job's steps
      (docs/experiments/2026-11-30-main-job-colour-match.md).
    - Pixels: two 1 x 1 convolutions softly assign every pixel of the current frame to one of the C named colours
      or to a last class, no named colour (sky, ground, roads); each cell gets its histogram of them.
    - Match: a cell's match logit is `weight` x log(sum_c named_c h_c + MATCH_FLOOR), the share of its pixels in
      the colour named (its probabilities detached: the cells do not move what is named). It joins the cell's
      score, and its own cross-entropy over the cells (`colour_cell_loss`) trains the pixel classifier to find the
      named colour in the target's cell. A landmark covering 3 % of a cell moves that share from near 0 to 0.03,
      which the log turns into a large difference.

    Args:
        llm_dim: the width of the prompt's input embeddings.
        colours: C named colours (the colour vocabulary of `TARGET_ATTRIBUTES`).
        grid_side: cells per side of the current frame's token grid.
    """

    MATCH_FLOOR = 1e-3  # keeps log(match) finite in a cell without the colour
    PIXEL_HIDDEN = 16  # width of the per-pixel classifier
    # the pixel classifier's input (RGB in [-GAIN / 2, GAIN / 2]) and its logits (GAIN x the last convolution) are
    # scaled, its weights started GAIN times smaller: the same function at the start, but an optimizer step that
    # moves each weight by about lr (Adam) moves it GAIN times faster, as the classifier must learn within the
    # main job's steps
    GAIN = 10.0

    def __init__(self, llm_dim: int, colours: int, grid_side: int) -> None:
        super().__init__()
        self.grid_side = grid_side
        self.pixel_classes = nn.Sequential(
            nn.Conv2d(3, self.PIXEL_HIDDEN, 1), nn.GELU(), nn.Conv2d(self.PIXEL_HIDDEN, colours + 1, 1)
        )
        # a word's score: w_0 . e + (relative place) x w_1 . e, e its normalised input embedding
        self.word_score = nn.Linear(llm_dim, 2, bias=False)
        self.word_colours = nn.Linear(llm_dim, colours)
        self.weight = nn.Parameter(torch.ones(()))

    def init_weights(self) -> None:
        """Per-pixel classes that already differ between colours (a classifier that starts uniform gives every cell
        the same match)."""
        for conv in (self.pixel_classes[0], self.pixel_classes[2]):
            init.normal_(conv.weight, std=1.0 / self.GAIN)
            init.zeros_(conv.bias)
        width = self.word_colours.in_features
        init.normal_(self.word_score.weight, std=width**-0.5)
        init.normal_(self.word_colours.weight, std=width**-0.5)
        init.zeros_(self.word_colours.bias)
        init.ones_(self.weight)

    def histogram(self, pixels: torch.Tensor) -> torch.Tensor:
        """(F, 3, H, W) uint8 RGB -> (F, P, C + 1) each cell's share of pixels in each named colour and in none
        (rows sum to 1)."""
        dtype = self.word_colours.weight.dtype
        x = (pixels.to(dtype) / 255.0 - 0.5) * self.GAIN  # (F, 3, H, W)
        shares = (self.pixel_classes(x) * self.GAIN).softmax(dim=1)  # (F, C + 1, H, W)
        cell = pixels.shape[-1] // self.grid_side
        return F.avg_pool2d(shares, cell).flatten(2).transpose(1, 2)  # (F, P, C + 1)

    def name_colour(self, words: torch.Tensor, word_mask: torch.Tensor) -> torch.Tensor:
        """words (B, L, D_llm) input embeddings, word_mask (B, L) bool the prompt's positions -> (B, C) logits of
        the colour the prompt names for the target."""
        x = (
            F.normalize(words.to(self.word_colours.weight.dtype), dim=-1) * words.shape[-1] ** 0.5
        )  # (B, L, D)
        mask = word_mask.to(x.device)
        count = mask.sum(dim=1, keepdim=True).clamp(min=1)  # (B, 1)
        place = mask.cumsum(dim=1).to(x.dtype) / count  # (B, L): (0, 1], 1 at the last word
        parts = self.word_score(x)  # (B, L, 2)
        score = (parts[..., 0] + place * parts[..., 1]).masked_fill(~mask, float("-inf"))  # (B, L)
        pooled = (score.softmax(dim=1).nan_to_num(0.0)[..., None] * x).sum(dim=1)  # (B, D)
        return self.word_colours(pooled)  # (B, C)

    def ask(self, colour_logits: torch.Tensor) -> torch.Tensor:
        """(B, C) named-colour logits -> (B, C + 1) the classes asked for: the named colours' probabilities
        (detached), never the last class (no named colour)."""
        named = colour_logits.detach().softmax(dim=-1)  # (B, C)
        return F.pad(named, (0, 1))  # (B, C + 1)

    def forward(self, colours: torch.Tensor, colour_logits: torch.Tensor) -> torch.Tensor:
        """colours (B, P, C + 1) cell histograms, colour_logits (B, C) the named colour -> (B, P) match logits."""
        asked = self.ask(colour_logits)  # (B, C + 1)
        match = (colours.to(asked.dtype) * asked[:, None]).sum(dim=-1)  # (B, P)
        return self.weight * torch.log(match + self.MATCH_FLOOR)


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
        self.colour_vocabulary = (
            ColourVocabulary(llm_dim, cfg.attribute_classes[0], grid_side) if cfg.colour_vocabulary else None
        )

    def init_weights(self) -> None:
        super().init_weights()
        if self.colour_vocabulary is not None:
            self.colour_vocabulary.init_weights()

    def forward(
        self,
        hidden: torch.Tensor,
        key_mask: torch.Tensor,
        image_positions: torch.Tensor,
        last_positions: torch.Tensor,
        visual_cells: torch.Tensor | None = None,
        colours: torch.Tensor | None = None,
        words: torch.Tensor | None = None,
        word_mask: torch.Tensor | None = None,
    ) -> GroundingOutput:
        """Predict one box per sequence.

        Args:
            hidden: (B, L, D_llm) last-layer LLM hidden states.
            key_mask: (B, L) bool, positions the head may read (image + prompt, never padding/targets).
            image_positions: (B, P) long, positions of the current frame's tokens.
            last_positions: (B,) long, position of each row's last prompt token.
            visual_cells: (B, P, D_llm) the current frame's visual tokens, the LLM's inputs at `image_positions`
                (needed with `visual_skip`).
            colours: (B, P, C + 1) the current frame's cell colour histograms (`ColourVocabulary.histogram`; needed
                with `colour_vocabulary`).
            words: (B, L, D_llm) the LLM's input embeddings, with word_mask (B, L) bool the prompt's positions
                (`SequenceLayout.prompt_mask`; needed with `colour_vocabulary`).
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
        word_colours = match_logits = None
        if self.colour_vocabulary is not None:
            if colours is None or words is None or word_mask is None:
                raise ValueError(
                    "grounding.colour_vocabulary needs the current frame's cell colours (colours) and the prompt's"
                    " input embeddings (words, word_mask)"
                )
            word_colours = self.colour_vocabulary.name_colour(words, word_mask)  # (B, C)
            match_logits = self.colour_vocabulary(colours, word_colours)  # (B, P)
            cell_logits = cell_logits + match_logits
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
        return GroundingOutput(
            boxes,
            reading.visibility,
            cell_logits,
            query_attributes,
            cell_attributes,
            word_colours,
            match_logits,
        )


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
    attribute_weight * `attribute_loss` (when the head classifies attributes and the batch has them), + the
    cross-entropy of the colour the prompt's words name (`word_colour_loss`) and that of the target's cell from the
    colour match alone (`colour_cell_loss`), each weight 1, with a colour vocabulary.

    Args:
        output: the head's prediction (boxes (B, 4) cxcywh, visibility logits (B,), cell logits (B, P) or None).
        target_boxes: (B, 4) ground truth cxcywh (ignored where not visible).
        visible: (B,) bool ground-truth visibility mask.
        cfg: grounding config (weights).
        attributes: (B, 4) long target attribute ids, -1 where unknown (None: no attribute term).

    Returns:
        The scalar loss and float logs: `box_iou` (mean IoU over visible boxes, 0 when none),
        `num_visible_boxes`, `giou_loss`, `l1_loss`, `visibility_loss`, `cell_loss` (and `attribute_loss`,
        `query_color_accuracy`, `cell_color_accuracy` with the attribute term; `word_colour_loss`,
        `word_color_accuracy`, `colour_cell_loss` with a colour vocabulary).
    """
    pred_boxes, visibility_logits = output.boxes, output.visibility
    visible = visible.bool()
    count = int(visible.sum())
    zero = pred_boxes.sum() * 0.0  # keeps the graph when no box is visible
    cell_term = colour_cell_term = zero
    if count:
        target = target_boxes[visible].to(pred_boxes.device)
        iou, giou = iou_and_giou(pred_boxes[visible], target)
        giou_term = (1.0 - giou).mean()
        l1_term = F.l1_loss(pred_boxes[visible].float(), target.float(), reduction="none")
        l1_term = l1_term.sum(-1).mean()
        if output.cell_logits is not None:
            side = int(round(output.cell_logits.shape[-1] ** 0.5))
            target_cells = box_cells(target, side)  # (V,)
            cell_term = F.cross_entropy(output.cell_logits[visible].float(), target_cells)
            if output.match_logits is not None:  # the colour match alone, against the same cells
                colour_cell_term = F.cross_entropy(output.match_logits[visible].float(), target_cells)
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
    if output.word_colours is not None:
        word_term, word_logs = word_colour_loss(output.word_colours, attributes)
        loss = loss + word_term
        attribute_logs.update(word_logs)
    if output.match_logits is not None:  # in the graph through cell_logits when no box is visible
        loss = loss + colour_cell_term
        attribute_logs["colour_cell_loss"] = float(colour_cell_term.detach())
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


def word_colour_loss(
    word_colours: torch.Tensor, attributes: torch.Tensor | None
) -> tuple[torch.Tensor, dict[str, float]]:
    """Cross-entropy of the target's colour (attributes[:, 0], -1 skipped; None: no labels) from (B, C)
    `word_colours` logits, and its logs `word_colour_loss` and `word_color_accuracy` (absent when no row has a
    known colour)."""
    term = word_colours.sum() * 0.0  # in the graph when no row has a known colour (DDP needs every gradient)
    logs = {}
    labels = None if attributes is None else attributes[:, 0].to(word_colours.device).long()  # (B,)
    known = None if labels is None else labels >= 0  # (B,)
    if known is not None and bool(known.any()):
        logits = word_colours[known].float()  # (n, C)
        term = term + F.cross_entropy(logits, labels[known])
        logs["word_color_accuracy"] = float((logits.argmax(dim=-1) == labels[known]).float().mean())
    logs["word_colour_loss"] = float(term.detach())
    return term, logs


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
