"""A shuffling sampler whose order depends only on (seed, epoch), cut to whole global batches."""

from __future__ import annotations

from collections.abc import Iterator

import torch
from torch.utils.data import Sampler


class EpochShuffleSampler(Sampler[int]):
    """A permutation of `range(num_samples)` drawn from `seed + epoch`, cut to whole global batches.

    Every optimizer step consumes exactly `global_batch_size` samples, whatever the number of processes: the
    accelerate batch-sampler shard hands micro-batch i to process `i % world_size`, so the first
    `global_batch_size` indices of the epoch always form step 0's batch. Truncating to a multiple of
    `global_batch_size` keeps every epoch a whole number of steps (the last partial batch is dropped, as
    `drop_last` would) and makes the order reproducible and resumable.

    Args:
        num_samples: dataset length.
        global_batch_size: samples per optimizer step across all processes and accumulation steps.
        seed: base seed; epoch `e` uses `seed + e`.
    """

    def __init__(self, num_samples: int, global_batch_size: int, seed: int) -> None:
        if global_batch_size <= 0:
            raise ValueError(f"global_batch_size must be positive, got {global_batch_size}")
        if num_samples < global_batch_size:
            raise ValueError(
                f"the dataset has {num_samples} samples, fewer than one global batch ({global_batch_size}): "
                "lower batch.global_batch_size or use a larger dataset"
            )
        self.num_samples = num_samples
        self.global_batch_size = global_batch_size
        self.seed = seed
        self.epoch = 0

    @property
    def steps_per_epoch(self) -> int:
        """Optimizer steps in one epoch."""
        return self.num_samples // self.global_batch_size

    def set_epoch(self, epoch: int) -> None:
        """Select the permutation of `epoch` (called by the loop, and by accelerate's loader wrapper)."""
        self.epoch = epoch

    def __len__(self) -> int:
        return self.steps_per_epoch * self.global_batch_size

    def __iter__(self) -> Iterator[int]:
        generator = torch.Generator().manual_seed(self.seed + self.epoch)
        order = torch.randperm(self.num_samples, generator=generator)
        return iter(order[: len(self)].tolist())
