"""Offline evaluation on held-out samples: loss, action accuracy and box IoU, exact over processes."""

from __future__ import annotations

import logging

import numpy as np
import torch
from accelerate import Accelerator
from accelerate.utils import send_to_device
from torch.utils.data import DataLoader, Dataset, Subset

from openfly_agent import constants as C

logger = logging.getLogger(__name__)


def eval_indices(num_samples: int, max_samples: int | None, multiple: int) -> list[int]:
    """Evenly spaced sample indices, as many as possible up to `max_samples`, a whole multiple of `multiple`.

    A multiple of (processes x per-device batch) gives every process the same number of full batches, so the
    figures need no padding (exact) and sharded models (FSDP, ZeRO-3) run the same number of forwards
    everywhere. At most `multiple - 1` samples of the split are left out.
    """
    wanted = num_samples if max_samples is None else min(max_samples, num_samples)
    count = (wanted // multiple) * multiple
    if count == 0:
        return []
    return ((np.arange(count) * num_samples) // count).tolist()  # distinct, evenly spaced, starts at 0


def make_eval_loader(
    dataset: Dataset,
    max_samples: int | None,
    batch_size: int,
    accelerator: Accelerator,
    collate_fn,
    num_workers=0,
) -> tuple[DataLoader | None, list[int]]:
    """This process's shard of an evenly spaced evaluation subset (see `eval_indices`), in a plain DataLoader.

    Returns:
        The loader (None when the split is smaller than one batch per process) and the subset's indices (all
        processes).
    """
    world, rank = accelerator.num_processes, accelerator.process_index
    indices = eval_indices(len(dataset), max_samples, batch_size * world)
    if not indices:
        logger.warning(
            "evaluation split has %d samples, fewer than one batch per process: skipped", len(dataset)
        )
        return None, []
    shard = Subset(dataset, indices[rank::world])
    loader = DataLoader(
        shard, batch_size=batch_size, shuffle=False, collate_fn=collate_fn, num_workers=num_workers
    )
    return loader, indices


@torch.no_grad()
def evaluate(model: torch.nn.Module, loader: DataLoader, accelerator: Accelerator) -> dict[str, float]:
    """Loss, action accuracy (per sample) and box IoU (per visible box) over every process's shard.

    Batch means from `model(batch) -> (loss, logs)` are weighted by the batch size (loss, accuracy) and by the
    number of visible boxes (IoU), then summed over processes, so the figures equal a single pass over the
    whole subset.
    """
    was_training = model.training
    model.eval()
    # samples, loss x B, accuracy x B, IoU x visible, visible
    sums = torch.zeros(5, dtype=torch.float64, device=accelerator.device)
    for batch in loader:
        batch = send_to_device(batch, accelerator.device)
        loss, logs = model(batch)
        size = float(batch[C.INPUT_IDS].shape[0])
        visible = float(batch[C.BOX_VISIBLE].sum()) if C.BOX_VISIBLE in batch else 0.0
        iou = float(logs.get("box_iou", float("nan")))
        sums += torch.tensor(
            [
                size,
                float(loss) * size,
                float(logs["action_accuracy"]) * size,
                iou * visible if visible and iou == iou else 0.0,
                visible if iou == iou else 0.0,
            ],
            dtype=torch.float64,
            device=accelerator.device,
        )
    if accelerator.num_processes > 1:
        sums = accelerator.reduce(sums, reduction="sum")
    model.train(was_training)
    samples, loss, accuracy, iou, visible = sums.tolist()
    if samples == 0:
        return {}
    return {
        "loss": loss / samples,
        "action_accuracy": accuracy / samples,
        "box_iou": iou / visible if visible else float("nan"),
        "samples": samples,
    }
