"""`SequenceLayout`: the one place that knows the order of a step's token segments.

One step reads `[BOS] [memory, oldest first] [current frame] [prompt] [BOX] [action]` (`SEGMENTS`). Training
rows are right padded and hold every segment (BOX when the action head has a box token, the action when the row
is labelled); an inference prefill is left padded and stops after the prompt, and BOX and decoded action tokens
follow it one cached step at a time (`then`). Both are built here, segment by segment in `SEGMENTS` order, so a
new segment is one edit: a name in `SEGMENTS` and its piece in `for_training` / `for_inference`.

Masked-out visual slots (missing keyframe sets) and padding take no position: positions count only the attended
tokens, so a right-padded training row, a left-padded inference row and an unpadded single row give every real
token the same position.

Right-padded rows also run in length groups (`run_in_length_groups`, `llm.length_groups`): a grounding-stage
micro-batch mixes short referring expressions with long instructions, and a navigation batch mixes instructions of
different lengths; in one call every row is padded to the longest, and the tiny LLM spends about half its work on
padding. Rows are independent in a causal LM with a key padding mask and positions counted from the mask, so each
group can be cut to its own longest row, run alone, and padded back: every real position gets the hidden state of
the single call (up to float rounding of the different matmul shapes). Padding past a group's longest row gets
zeros; nothing reads padding.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

import torch
import torch.nn.functional as F

from openfly_agent.constants import IGNORE_INDEX

SEGMENTS = ("bos", "memory", "current", "prompt", "box", "action")  # the token order of one step
PADDING_RIGHT = "right"  # training: rows padded after their last token (length groups cut there)
PADDING_LEFT = "left"  # inference: rows end together, where the action is read
# a further length group must save at least this share of the padded batch's tokens: each call has a fixed cost
MIN_SAVING = 0.1


def position_ids_from_mask(attention_mask: torch.Tensor) -> torch.Tensor:
    """(B, L) mask -> (B, L) positions counting attended tokens only (0 on leading padding)."""
    return (attention_mask.long().cumsum(dim=-1) - 1).clamp(min=0)


def last_true_index(mask: torch.Tensor) -> torch.Tensor:
    """(B, L) bool -> (B,) index of each row's last True column (0 for an all-False row)."""
    columns = torch.arange(mask.shape[1], device=mask.device)[None]
    return (mask.long() * columns).amax(dim=1)


@dataclasses.dataclass(frozen=True)
class _Piece:
    """One segment of one row: (S, D) embeddings, (S,) long mask, (S,) long labels."""

    embeds: torch.Tensor
    mask: torch.Tensor
    labels: torch.Tensor


def _piece(
    embeds: torch.Tensor, mask: torch.Tensor | None = None, labels: torch.Tensor | None = None
) -> _Piece:
    """A segment; mask defaults to all attended, labels to IGNORE_INDEX (nothing to predict)."""
    n = embeds.shape[0]
    ones = torch.ones(n, dtype=torch.long, device=embeds.device)
    return _Piece(
        embeds,
        ones if mask is None else mask.long(),
        torch.full_like(ones, IGNORE_INDEX) if labels is None else labels,
    )


@dataclasses.dataclass(frozen=True)
class SequenceLayout:
    """The LLM input of one batch of steps and what the heads read in it.

    Attributes:
        embeds: (B, T, D) input embeddings to run: the whole rows, or after `then` only the T new tokens that
            follow a KV cache.
        mask: (B, L) long attention mask over every token so far (L = T without a cache); 0 on padding and on
            missing memory slots.
        positions: (B, T) long position ids of the tokens in `embeds`.
        labels: (B, L) long next-token targets (IGNORE_INDEX off the action), or None at inference.
        readable: (B, L) bool, what the grounding head may read: attended tokens that are no target and no BOX.
        first_image: (B,) long column of each row's first current-frame token.
        current: (B, P, D) the current frame's visual tokens as they entered the layout (grounding's skip).
        padding: `PADDING_RIGHT` (training) or `PADDING_LEFT` (inference).
    """

    embeds: torch.Tensor
    mask: torch.Tensor
    positions: torch.Tensor
    labels: torch.Tensor | None
    readable: torch.Tensor
    first_image: torch.Tensor
    current: torch.Tensor
    padding: str

    @classmethod
    def for_training(
        cls,
        text: torch.Tensor,
        attention_mask: torch.Tensor,
        labels: torch.Tensor,
        memory: torch.Tensor,
        memory_mask: torch.Tensor,
        current: torch.Tensor,
        box: torch.Tensor | None = None,
    ) -> SequenceLayout:
        """Right-padded training rows.

        Args:
            text: (B, L, D) embeddings of `[BOS] prompt action (+EOS) pad...` (right padded).
            attention_mask: (B, L) of the text.
            labels: (B, L) of the text, IGNORE_INDEX off the action; the action starts at a row's first label.
            memory: (B, M, D) memory tokens, oldest first; memory_mask: (B, M) bool, False on missing slots.
            current: (B, P, D) current-frame tokens.
            box: (B, D) the BOX token's embedding, or None (no box token); every row must then be labelled.

        Returns:
            The layout of (B, L + M + P (+1)) tokens.
        """
        labelled = labels != IGNORE_INDEX  # (B, L)
        if box is not None and not bool(labelled.any(dim=1).all()):
            raise ValueError("every row needs a labelled action token to put the box token before")
        starts = torch.where(labelled.any(dim=1), labelled.long().argmax(dim=1), labels.shape[1]).tolist()
        rows = []
        for row, start in enumerate(starts):
            rows.append(
                {
                    "bos": _piece(text[row, :1], attention_mask[row, :1], labels[row, :1]),
                    "memory": _piece(memory[row].to(text.dtype), memory_mask[row]),
                    "current": _piece(current[row].to(text.dtype)),
                    "prompt": _piece(text[row, 1:start], attention_mask[row, 1:start], labels[row, 1:start]),
                    "box": None if box is None else _piece(box[row, None].to(text.dtype)),
                    "action": _piece(text[row, start:], attention_mask[row, start:], labels[row, start:]),
                }
            )
        return cls._from_rows(rows, current, PADDING_RIGHT)

    @classmethod
    def for_inference(
        cls, prompts: list[torch.Tensor], memories: list[torch.Tensor], current: torch.Tensor
    ) -> SequenceLayout:
        """A left-padded prefill, up to the prompt (BOX and the action follow with `then`).

        Args:
            prompts: per row, the (L_i, D) embeddings of `[BOS] prompt`.
            memories: per row, (M_i, D) memory tokens, oldest first.
            current: (B, P, D) current-frame tokens.
        """
        dtype = prompts[0].dtype
        rows = [
            {
                "bos": _piece(prompt[:1]),
                "memory": _piece(memory.to(dtype)),
                "current": _piece(current[row].to(dtype)),
                "prompt": _piece(prompt[1:]),
            }
            for row, (prompt, memory) in enumerate(zip(prompts, memories, strict=True))
        ]
        layout = cls._from_rows(rows, current, PADDING_LEFT)
        return dataclasses.replace(layout, labels=None)

    @classmethod
    def _from_rows(cls, rows: list[dict[str, _Piece | None]], current: torch.Tensor, padding: str):
        """Concatenate each row's pieces in `SEGMENTS` order, pad the rows to one length and stack them."""
        unknown = {name for row in rows for name in row} - set(SEGMENTS)
        if unknown:
            raise ValueError(f"segments {sorted(unknown)} are not in SEGMENTS {SEGMENTS}")
        ordered = [[(name, row[name]) for name in SEGMENTS if row.get(name) is not None] for row in rows]
        lengths = [sum(piece.embeds.shape[0] for _, piece in row) for row in ordered]
        longest, ref = max(lengths), ordered[0][0][1].embeds
        embeds, mask, labels, is_box, first_image = [], [], [], [], []
        for row, length in zip(ordered, lengths, strict=True):
            pad = _Piece(  # no token: zeros, not attended, no target
                ref.new_zeros(longest - length, ref.shape[-1]),
                torch.zeros(longest - length, dtype=torch.long, device=ref.device),
                torch.full((longest - length,), IGNORE_INDEX, dtype=torch.long, device=ref.device),
            )
            row = [("pad", pad), *row] if padding == PADDING_LEFT else [*row, ("pad", pad)]
            names = [name for name, piece in row for _ in range(piece.embeds.shape[0])]  # (L,) segment names
            starts = [sum(piece.embeds.shape[0] for _, piece in row[:i]) for i in range(len(row))]
            embeds.append(torch.cat([piece.embeds for _, piece in row]))  # (L, D)
            mask.append(torch.cat([piece.mask for _, piece in row]))  # (L,)
            labels.append(torch.cat([piece.labels for _, piece in row]))  # (L,)
            is_box.append([name == "box" for name in names])
            first_image.append(starts[[name for name, _ in row].index("current")])
        mask, labels = torch.stack(mask), torch.stack(labels)  # (B, L), (B, L)
        is_box = torch.tensor(is_box, device=ref.device).reshape(mask.shape)  # (B, L)
        return cls(
            embeds=torch.stack(embeds),  # (B, L, D)
            mask=mask,
            positions=position_ids_from_mask(mask),
            labels=labels,
            readable=mask.bool() & (labels == IGNORE_INDEX) & ~is_box,
            first_image=torch.tensor(first_image, device=ref.device),  # (B,)
            current=current,
            padding=padding,
        )

    def then(self, token: torch.Tensor) -> SequenceLayout:
        """The next cached step: one (B, D) input embedding after every row (BOX, or a decoded action token)."""
        positions = position_ids_from_mask(self.mask)[:, -1:] + 1  # (B, 1)
        mask = torch.cat([self.mask, self.mask.new_ones(self.mask.shape[0], 1)], dim=1)  # (B, L + 1)
        return dataclasses.replace(
            self,
            embeds=token[:, None],
            mask=mask,
            positions=positions,
            labels=None,
            readable=torch.cat([self.readable, self.readable.new_zeros(self.mask.shape[0], 1)], dim=1),
        )

    # --- what the heads read ---------------------------------------------------------------------------
    def image_positions(self) -> torch.Tensor:
        """(B, P) long columns of each row's P current-frame tokens."""
        p = self.current.shape[1]
        return self.first_image[:, None] + torch.arange(p, device=self.first_image.device)[None]

    def prompt_mask(self) -> torch.Tensor:
        """(B, L) bool, each row's readable positions after its current frame: the prompt's words (a layout of
        whole rows, not a cached `then` step)."""
        columns = torch.arange(self.mask.shape[1], device=self.mask.device)[None]  # (1, L)
        after_frame = columns >= (self.first_image + self.current.shape[1])[:, None]  # (B, L)
        return self.readable & after_frame

    def action_reads(self) -> torch.Tensor:
        """(B, L - 1) bool, training: the positions whose next token is an action target."""
        if self.labels is None:
            raise ValueError("an inference layout has no targets: its action is read at the last position")
        return self.labels[:, 1:] != IGNORE_INDEX

    def action_targets(self) -> torch.Tensor:
        """(n,) long targets of `action_reads`, in row-major order."""
        return self.labels[:, 1:][self.action_reads()]


# --- length groups: right-padded rows cut to the longest row of their group ---------------------------------
def plan_length_groups(lengths: list[int], max_groups: int) -> list[list[int]]:
    """Split rows into at most `max_groups` groups, each a run of the rows sorted by length, so that the sum over
    groups of (rows x longest row) is smallest; a further group is kept only if it saves `MIN_SAVING` of the
    padded batch (rows x longest overall).

    Args:
        lengths: each row's length (last attended position + 1).
        max_groups: the most groups (1: one group, the batch as it is).

    Returns:
        Row indices per group, shortest rows first; the groups partition `range(len(lengths))`.
    """
    if max_groups < 1:
        raise ValueError(f"max_groups={max_groups} must be >= 1")
    order = sorted(range(len(lengths)), key=lambda row: (lengths[row], row))
    sorted_lengths = [lengths[row] for row in order]
    n = len(order)
    if n == 0:
        return []
    inf = float("inf")
    # best[g][j]: least cost of the first j sorted rows in g groups; cut[g][j]: where the last group starts
    best = [[inf] * (n + 1) for _ in range(max_groups + 1)]
    cut = [[0] * (n + 1) for _ in range(max_groups + 1)]
    best[0][0] = 0
    for g in range(1, max_groups + 1):
        for j in range(1, n + 1):
            for i in range(g - 1, j):
                cost = best[g - 1][i] + (j - i) * sorted_lengths[j - 1]
                if cost < best[g][j]:
                    best[g][j], cut[g][j] = cost, i
    padded = n * sorted_lengths[-1]
    groups = 1
    for g in range(2, max_groups + 1):
        if best[groups][n] - best[g][n] >= MIN_SAVING * padded:
            groups = g
    bounds, j = [], n
    for g in range(groups, 0, -1):
        bounds.append((cut[g][j], j))
        j = cut[g][j]
    return [order[start:end] for start, end in reversed(bounds)]


def run_in_length_groups(
    run: Callable[[torch.Tensor, torch.Tensor], torch.Tensor],
    embeds: torch.Tensor,
    mask: torch.Tensor,
    max_groups: int,
) -> torch.Tensor:
    """`run(embeds, mask)` (-> last hidden states) on groups of rows of similar length, reassembled in row order.

    Args:
        run: the decoder stack, (b, l, D) embeddings and (b, l) mask -> (b, l, D) hidden states.
        embeds: (B, L, D) right-padded input embeddings.
        mask: (B, L) attention mask (1 = attended; a row may have holes, e.g. missing memory slots).
        max_groups: the most groups (`plan_length_groups`); 1 runs the batch as it is.

    Returns:
        (B, L, D) hidden states; when grouped, zeros past the longest row of each row's group.
    """
    if max_groups == 1:  # one call: no lengths to read (a device sync on a GPU)
        return run(embeds, mask)
    lengths = (last_true_index(mask.bool()) + 1).tolist()
    groups = plan_length_groups(lengths, max_groups)
    if len(groups) <= 1:
        return run(embeds, mask)
    full = embeds.shape[1]
    outputs, order = [], []
    for rows in groups:
        longest = max(lengths[row] for row in rows)
        index = torch.tensor(rows, device=embeds.device)
        hidden = run(embeds[index, :longest], mask[index, :longest])  # (b, longest, D)
        outputs.append(F.pad(hidden, (0, 0, 0, full - longest)))  # (b, L, D)
        order.extend(rows)
    inverse = torch.empty(len(order), dtype=torch.long, device=embeds.device)
    inverse[torch.tensor(order, device=embeds.device)] = torch.arange(len(order), device=embeds.device)
    return torch.cat(outputs, dim=0)[inverse]  # (B, L, D), rows back in batch order
