"""Offline evaluation on held-out samples: loss, action accuracy and box IoU, exact over processes."""

from __future__ import annotations

import logging
from collections.abc import Callable

import numpy as np
import torch
from accelerate import Accelerator
from accelerate.utils import send_to_device
from torch.utils.data import DataLoader, Dataset

from openfly_agent import constants as C
from openfly_agent.utils.progress import progress_bar

logger = logging.getLogger(__name__)


def eval_indices(num_samples: int, max_samples: int | None) -> list[int]:
    """`min(max_samples, num_samples)` distinct, evenly spaced sample indices (all of them when None)."""
    count = num_samples if max_samples is None else min(max_samples, num_samples)
    if count <= 0:
        return []
    return ((np.arange(count) * num_samples) // count).tolist()  # distinct, evenly spaced, starts at 0


def shard_eval_batches(
    indices: list[int], world: int, rank: int, batch_size: int
) -> list[tuple[list[int], float]]:
    """Process `rank`'s evaluation batches as (sample indices, weight), covering `indices` exactly once overall.

    Whole groups of `world x batch_size` samples are dealt round-robin; the remainder (fewer than
    `world x batch_size`) is split across processes in one last batch each. A process whose share of the
    remainder is empty evaluates `indices[0]` with weight 0, so every process runs the same number of
    forwards (sharded models, FSDP / ZeRO-3, need that) and the weighted figures are exact.
    """
    if not indices:
        return []
    group = world * batch_size
    full = (len(indices) // group) * group
    mine = indices[:full][rank::world]
    batches = [(mine[i : i + batch_size], 1.0) for i in range(0, len(mine), batch_size)]
    remainder = indices[full:]
    if remainder:
        share = remainder[rank::world]
        batches.append((share, 1.0) if share else ([indices[0]], 0.0))
    return batches


class EvalBatches:
    """One process's evaluation batches; iterating yields (collated batch, weight), weight 0 for padding."""

    def __init__(self, dataset: Dataset, batches: list[tuple[list[int], float]], collate_fn, num_workers=0):
        self.weights = [weight for _, weight in batches]
        self.loader = DataLoader(
            dataset,
            batch_sampler=[sample_indices for sample_indices, _ in batches],
            collate_fn=collate_fn,
            num_workers=num_workers,
        )

    def __len__(self) -> int:
        return len(self.weights)

    def __iter__(self):
        return zip(self.loader, self.weights)


def make_eval_loader(
    dataset: Dataset,
    max_samples: int | None,
    batch_size: int,
    accelerator: Accelerator,
    collate_fn,
    num_workers=0,
) -> tuple[EvalBatches | None, list[int]]:
    """This process's shard (`shard_eval_batches`) of an evenly spaced evaluation subset (`eval_indices`).

    Returns:
        The batches (None when the split is empty) and the subset's indices (all processes).
    """
    indices = eval_indices(len(dataset), max_samples)
    if not indices:
        logger.warning("evaluation split is empty: skipped")
        return None, []
    batches = shard_eval_batches(indices, accelerator.num_processes, accelerator.process_index, batch_size)
    return EvalBatches(dataset, batches, collate_fn, num_workers), indices


@torch.no_grad()
def evaluate(
    model: torch.nn.Module,
    loader: EvalBatches,
    accelerator: Accelerator,
    desc: str | None = None,
    stop: Callable[[], bool] | None = None,
) -> dict[str, float] | None:
    """Loss, action accuracy (per sample; batches with action labels) and box IoU (per visible box) over every
    process's shard.

    Batch means from `model(batch) -> (loss, logs)` are weighted by the batch size (loss, accuracy) and by the
    number of visible boxes (IoU), times the batch's weight (0 for a padding batch), then summed over
    processes, so the figures equal a single pass over the whole subset.

    Args:
        desc: show a progress bar of this name (main process), as the training loop does.
        stop: asked before every batch; True (the same on every process, e.g. `StopFlags.reason() ==
            "signal"`) abandons the pass and returns None: no partial figures.
    """
    was_training = model.training
    model.eval()
    bar = progress_bar(total=len(loader), desc=desc, disable=desc is None or not accelerator.is_main_process)
    with bar:
        sums, has_actions, stopped = _accumulate(model, loader, accelerator, bar, stop)
    model.train(was_training)
    if stopped:
        return None
    if accelerator.num_processes > 1:
        sums = accelerator.reduce(sums, reduction="sum")
    samples, loss, accuracy, iou, visible = sums.tolist()
    if samples == 0:
        return {}
    metrics = {
        "loss": loss / samples,
        "box_iou": iou / visible if visible else float("nan"),
        "samples": samples,
    }
    if has_actions:  # grounding batches carry no action targets
        metrics["action_accuracy"] = accuracy / samples
    return metrics


def _accumulate(model, loader: EvalBatches, accelerator: Accelerator, bar, stop):
    """The weighted sums of `evaluate` over this process's batches; (sums, has_actions, stopped)."""
    # samples, loss x B, accuracy x B, IoU x visible, visible
    sums = torch.zeros(5, dtype=torch.float64, device=accelerator.device)
    has_actions = False
    for batch, weight in loader:
        if stop is not None and stop():
            return sums, has_actions, True
        batch = send_to_device(batch, accelerator.device)
        has_actions = has_actions or C.LABELS in batch
        loss, logs = model(batch)
        size = float(batch[C.INPUT_IDS].shape[0])
        visible = float(batch[C.BOX_VISIBLE].sum()) if C.BOX_VISIBLE in batch else 0.0
        iou = float(logs.get("box_iou", float("nan")))
        sums += weight * torch.tensor(
            [
                size,
                float(loss) * size,
                float(logs.get("action_accuracy", 0.0)) * size,
                iou * visible if visible and iou == iou else 0.0,
                visible if iou == iou else 0.0,
            ],
            dtype=torch.float64,
            device=accelerator.device,
        )
        bar.update(1)
    return sums, has_actions, False
