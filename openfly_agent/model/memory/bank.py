"""Grid pooling of patch tokens and the per-episode FIFO memory bank of pooled keyframe tokens."""

from __future__ import annotations

import math
from collections import OrderedDict
from collections.abc import Hashable

import torch
import torch.nn.functional as F


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


class MemoryBank:
    """FIFO of at most `capacity` entries (pooled keyframe-set tokens), keyed so a set is stored once.

    Args:
        capacity: K; pushing onto a full bank evicts the oldest entry.
    """

    def __init__(self, capacity: int) -> None:
        if capacity < 0:
            raise ValueError(f"MemoryBank capacity={capacity} must be >= 0")
        self.capacity = capacity
        self._entries: OrderedDict[Hashable, torch.Tensor] = OrderedDict()

    def __len__(self) -> int:
        return len(self._entries)

    def __contains__(self, key: Hashable) -> bool:
        return key in self._entries

    def push(self, key: Hashable, tokens: torch.Tensor) -> list[Hashable]:
        """Append `tokens` under `key` (already stored: no change); returns the evicted keys, oldest first."""
        if self.capacity == 0 or key in self._entries:
            return []
        self._entries[key] = tokens
        evicted = []
        while len(self._entries) > self.capacity:
            evicted.append(self._entries.popitem(last=False)[0])
        return evicted

    def keys(self) -> list[Hashable]:
        """Stored keys, oldest first."""
        return list(self._entries)

    def tokens(self) -> list[torch.Tensor]:
        """Stored token tensors, oldest first."""
        return list(self._entries.values())

    def clear(self) -> None:
        """Forget everything (episode reset)."""
        self._entries.clear()
