"""Run the decoder stack on a right-padded batch in groups of rows of similar length (`llm.length_groups`).

A grounding-stage micro-batch mixes short referring expressions with long instructions, and a navigation batch
mixes instructions of different lengths: in one call every row is padded to the longest, and the tiny LLM
spends about half its work on padding. Rows are independent in a causal LM with a key padding mask and
positions counted from the mask (model/layout.py), so each group can be cut to its own longest row, run alone,
and padded back: every real position gets the hidden state of the single call (up to float rounding of the
different matmul shapes). Padding past a group's longest row gets zeros; nothing reads padding.
"""

from __future__ import annotations

from collections.abc import Callable

import torch
import torch.nn.functional as F

from openfly_agent.model.grounding.box_token import last_true_index

# a further group must save at least this share of the padded batch's tokens: each call has a fixed cost
MIN_SAVING = 0.1


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
