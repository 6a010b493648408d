"""Visual token merging (VTM) of a keyframe set into its reference frame, and grid pooling of patch tokens: how a
memory entry's tokens shrink; pure, batched tensor functions.

Each token of a comparative frame finds its most similar reference token (cosine). It is merged into it
when the similarity is >= threshold (and, with top_r, it is among the r best of its frame); a reference
token becomes the plain average of itself and everything merged into it. Unmerged comparative tokens are
dropped, so a set always leaves P tokens (the reference frame's layout), whatever its size. `grid_pool` then
averages g x g windows of those tokens (the keyframe memory; the OpenVLA-compatible history pools each frame).
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F


def choose_reference(
    boxes: torch.Tensor, box_visible: torch.Tensor, frame_mask: torch.Tensor
) -> torch.Tensor:
    """Index of the reference frame of each set: the real frame with the largest visible box.

    Ties go to the earliest frame. A set with no visible box uses its middle real frame (for a complete
    set that is the change-point frame).

    Args:
        boxes: (N, S, 4) (cx, cy, w, h) in [0, 1].
        box_visible: (N, S) bool.
        frame_mask: (N, S) bool, real frames.

    Returns:
        (N,) long frame index per set (0 for sets without any real frame).
    """
    area = boxes[..., 2].clamp(min=0) * boxes[..., 3].clamp(min=0)  # (N, S)
    usable = box_visible & frame_mask
    scored = torch.where(usable, area, torch.full_like(area, -1.0))  # (N, S)
    largest = torch.argmax(scored, dim=1)  # first maximum
    real_count = frame_mask.sum(dim=1)  # (N,)
    rank = torch.cumsum(frame_mask.long(), dim=1) - 1  # (N, S) rank among real frames
    middle = (frame_mask & (rank == (real_count // 2)[:, None])).float().argmax(dim=1)  # (N,)
    return torch.where(usable.any(dim=1), largest, middle)


def merge_into_reference(
    frames: torch.Tensor,
    frame_mask: torch.Tensor,
    reference_index: torch.Tensor,
    threshold: float | None = 0.9,
    top_r: int | None = None,
) -> torch.Tensor:
    """Merge the comparative frames of each set into its reference frame.

    Args:
        frames: (N, S, P, D) token features of each frame of each set.
        frame_mask: (N, S) bool, real frames (padding frames never merge).
        reference_index: (N,) long, the reference frame of each set.
        threshold: cosine similarity a token needs to merge (None: no threshold, top_r alone decides).
        top_r: at most this many tokens of each comparative frame merge (its most similar ones).

    Returns:
        (N, P, D) merged reference tokens.
    """
    if threshold is None and top_r is None:
        raise ValueError("merge_into_reference needs a threshold or top_r")
    n, s, p, d = frames.shape
    batch = torch.arange(n, device=frames.device)
    reference = frames[batch, reference_index]  # (N, P, D)
    comparative = frame_mask.clone()
    comparative[batch, reference_index] = False  # (N, S)

    sim = torch.einsum(
        "nspd,nqd->nspq", F.normalize(frames.float(), dim=-1), F.normalize(reference.float(), dim=-1)
    )  # (N, S, P, P): comparative token p vs reference token q
    best_sim, best_ref = sim.max(dim=-1)  # (N, S, P)
    merge = comparative[:, :, None].expand(n, s, p)  # (N, S, P)
    if threshold is not None:
        merge = merge & (best_sim >= threshold)
    if top_r is not None:
        merge = merge & _top_r_mask(best_sim.masked_fill(~merge, float("-inf")), top_r)

    weights = merge.to(frames.dtype)  # (N, S, P)
    index = best_ref.reshape(n, s * p)  # (N, S*P) target reference token of each comparative token
    sums = reference.clone().scatter_add_(
        1, index[..., None].expand(n, s * p, d), (frames * weights[..., None]).reshape(n, s * p, d)
    )  # (N, P, D)
    counts = torch.ones(n, p, dtype=frames.dtype, device=frames.device).scatter_add_(
        1, index, weights.reshape(n, s * p)
    )  # (N, P)
    return sums / counts[..., None]


def _top_r_mask(scores: torch.Tensor, r: int) -> torch.Tensor:
    """(N, S, P) bool: the r highest finite scores of each (n, s) row."""
    r = min(r, scores.shape[-1])
    if r == 0:
        return torch.zeros_like(scores, dtype=torch.bool)
    top = torch.topk(scores, r, dim=-1).indices  # (N, S, r)
    mask = torch.zeros_like(scores, dtype=torch.bool).scatter_(-1, top, True)
    return mask & torch.isfinite(scores)


def grid_pool(tokens: torch.Tensor, grid: int) -> torch.Tensor:
    """Average-pool square patch tokens in g x g windows: (N, P, D) -> (N, (sqrt(P) / g)^2, D).

    g = sqrt(P) gives one token per frame (OpenFly's `grid_size=16` on 224 px); g = 1 is the identity.
    """
    n, p, d = tokens.shape
    side = math.isqrt(p)
    if side * side != p:
        raise ValueError(f"grid_pool needs a square patch grid, got P={p} tokens")
    if side % grid:
        raise ValueError(f"grid_pool: grid {grid} must divide the patch grid side {side}")
    maps = tokens.transpose(1, 2).reshape(n, d, side, side)  # (N, D, s, s)
    pooled = F.avg_pool2d(maps, kernel_size=grid, stride=grid)  # (N, D, s/g, s/g)
    return pooled.flatten(2).transpose(1, 2)  # (N, (s/g)^2, D)
