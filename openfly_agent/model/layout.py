"""`SequenceLayout`: the one place that knows the order of a step's token segments.

One step reads `[BOS] [memory, oldest first] [current frame] [prompt] [BOX] [action]` (`SEGMENTS`). Training
rows are right padded and hold every segment (BOX when the action head has a box token, the action when the row
is labelled); an inference prefill is left padded and stops after the prompt, and BOX and decoded action tokens
follow it one cached step at a time (`then`). Both are built here, segment by segment in `SEGMENTS` order, so a
new segment is one edit: a name in `SEGMENTS` and its piece in `for_training` / `for_inference`.

Masked-out visual slots (missing keyframe sets) and padding take no position: positions count only the attended
tokens, so a right-padded training row, a left-padded inference row and an unpadded single row give every real
token the same position.
"""

from __future__ import annotations

import dataclasses

import torch

from openfly_agent.constants import IGNORE_INDEX

SEGMENTS = ("bos", "memory", "current", "prompt", "box", "action")  # the token order of one step
PADDING_RIGHT = "right"  # training: rows padded after their last token (length groups cut there)
PADDING_LEFT = "left"  # inference: rows end together, where the action is read


def position_ids_from_mask(attention_mask: torch.Tensor) -> torch.Tensor:
    """(B, L) mask -> (B, L) positions counting attended tokens only (0 on leading padding)."""
    return (attention_mask.long().cumsum(dim=-1) - 1).clamp(min=0)


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
    def action_reads(self) -> torch.Tensor:
        """(B, L - 1) bool, training: the positions whose next token is an action target."""
        if self.labels is None:
            raise ValueError("an inference layout has no targets: its action is read at the last position")
        return self.labels[:, 1:] != IGNORE_INDEX

    def action_targets(self) -> torch.Tensor:
        """(n,) long targets of `action_reads`, in row-major order."""
        return self.labels[:, 1:][self.action_reads()]
