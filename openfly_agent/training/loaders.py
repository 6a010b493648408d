"""The training DataLoader (seeded order, whole global batches) and the batches of one epoch."""

from __future__ import annotations

import logging
from collections.abc import Iterable

import torch
from accelerate import Accelerator
from torch.utils.data import DataLoader

from openfly_agent.data.dataset import NavigationStepDataset
from openfly_agent.training.config import TrainConfig
from openfly_agent.training.sampler import EpochShuffleSampler
from openfly_agent.training.state import TrainerState

logger = logging.getLogger(__name__)


def make_train_loader(
    dataset: NavigationStepDataset, collate_fn, cfg: TrainConfig
) -> tuple[DataLoader, EpochShuffleSampler]:
    """Per-device micro-batches in the order of an `EpochShuffleSampler` (seed, epoch, global batch)."""
    sampler = EpochShuffleSampler(len(dataset), cfg.batch.global_batch_size, cfg.seed)
    loader = DataLoader(
        dataset,
        batch_size=cfg.batch.per_device_batch_size,
        sampler=sampler,
        drop_last=True,
        collate_fn=collate_fn,
        num_workers=cfg.data.num_workers,
        persistent_workers=False,  # fresh workers each epoch see the dataset's current epoch (random history)
        generator=torch.Generator().manual_seed(cfg.seed),  # keeps the global torch RNG out of data loading
    )
    return loader, sampler


def epoch_batches(
    loader: DataLoader, dataset: NavigationStepDataset, state: TrainerState, accelerator: Accelerator
) -> Iterable[dict]:
    """The prepared train loader for `state.epoch`, skipping the micro-batches of this epoch already consumed.

    The epoch goes to the sampler (through the prepared loader) and to the dataset directly: accelerate's loader
    forwards it to the dataset only when it has no sharded batch sampler, i.e. with one process.
    """
    loader.set_epoch(state.epoch)
    dataset.set_epoch(state.epoch)  # the "random" history draws of this epoch, under every launcher
    skip = state.step_in_epoch * accelerator.gradient_accumulation_steps
    if not skip:
        return loader
    logger.info(
        "resuming epoch %d after %d steps (%d micro-batches skipped)", state.epoch, state.step_in_epoch, skip
    )
    return accelerator.skip_first_batches(loader, skip)
