"""AdamW with decay only on matrices, and the lr schedule (constant | cosine | linear, with warmup)."""

from __future__ import annotations

import logging
import math
from collections.abc import Iterable

import torch
from torch import nn

logger = logging.getLogger(__name__)

SCHEDULES = ("constant", "cosine", "linear")


class ScheduleClock:
    """The fraction of a run's time budget already used, as the schedule reads it (0 for a step horizon).

    The trainer sets `fraction` after every optimizer step from the time every process agrees on
    (training/stops.py), so all processes apply the same learning rate.
    """

    def __init__(self) -> None:
        self.fraction = 0.0


def make_param_groups(model: nn.Module, weight_decay: float) -> list[dict]:
    """Split the trainable parameters into a decayed group (matrices) and an undecayed one (biases, norms).

    Frozen parameters (`requires_grad=False`) are left out, so the optimizer state only covers what trains.
    If the model offers `get_optim_params()` (param groups of its own, e.g. a separate backbone lr), each of
    its groups is split the same way and keeps its own options.
    """
    if hasattr(model, "get_optim_params"):
        groups = list(model.get_optim_params())
        if groups and not isinstance(groups[0], dict):  # a plain iterable of parameters
            groups = [{"params": groups}]
    else:
        groups = [{"params": list(model.parameters())}]
    split_groups = []
    for group in groups:
        params = [p for p in group["params"] if p.requires_grad]
        options = {k: v for k, v in group.items() if k != "params"}
        decay = [p for p in params if p.ndim >= 2]
        no_decay = [p for p in params if p.ndim < 2]
        if decay:
            split_groups.append({**options, "params": decay, "weight_decay": weight_decay})
        if no_decay:
            split_groups.append({**options, "params": no_decay, "weight_decay": 0.0})
    if not split_groups:
        raise ValueError(
            "The model has no trainable parameters: check the freeze stage and the LoRA settings"
        )
    return split_groups


def count_parameters(params: Iterable[torch.Tensor]) -> int:
    """Number of scalar values in `params` (each tensor counted once)."""
    seen: dict[int, int] = {}
    for p in params:
        seen[id(p)] = p.numel()
    return sum(seen.values())


def make_optimizer(
    model: nn.Module,
    lr: float,
    weight_decay: float,
    betas: tuple[float, float],
    eps: float = 1e-8,
    fused: bool = False,
) -> torch.optim.AdamW:
    """AdamW over the trainable parameters of `model` (see `make_param_groups`); `fused`: PyTorch's fused
    kernel (one launch for every tensor) instead of the default for-each implementation."""
    groups = make_param_groups(model, weight_decay)
    trainable = count_parameters(p for g in groups for p in g["params"])
    total = count_parameters(model.parameters())
    logger.info(
        "optimizer: AdamW%s lr=%g wd=%g over %d / %d parameters (%.2f%%)",
        " (fused)" if fused else "",
        lr,
        weight_decay,
        trainable,
        total,
        100.0 * trainable / max(total, 1),
    )
    return torch.optim.AdamW(groups, lr=lr, betas=betas, eps=eps, **({"fused": True} if fused else {}))


def lr_multiplier(
    step: int,
    schedule: str,
    warmup_steps: int,
    total_steps: int,
    min_lr_ratio: float = 0.0,
    time_fraction: float = 0.0,
) -> float:
    """The factor applied to the base lr after `step` optimizer steps (step 0 is the first update).

    Warmup ramps linearly from 1/(warmup_steps+1) to 1 over `warmup_steps` steps; then `constant` stays at 1,
    `cosine` follows half a cosine down to `min_lr_ratio` at `total_steps`, `linear` falls in a straight line
    to `min_lr_ratio` at `total_steps`. With a time budget, `time_fraction` is the part of it already used:
    the decay is as far along as the further of the two budgets (a run cut by its time limit ends low).
    """
    if schedule not in SCHEDULES:
        raise ValueError(f"optim.schedule must be one of {SCHEDULES}, got {schedule!r}")
    if step < warmup_steps:
        return (step + 1) / (warmup_steps + 1)
    if schedule == "constant":
        return 1.0
    decay_steps = max(total_steps - warmup_steps, 1)
    progress = min(max((step - warmup_steps) / decay_steps, time_fraction), 1.0)
    if schedule == "cosine":
        shape = 0.5 * (1.0 + math.cos(math.pi * progress))
    else:
        shape = 1.0 - progress
    return min_lr_ratio + (1.0 - min_lr_ratio) * shape


def make_scheduler(
    optimizer: torch.optim.Optimizer,
    schedule: str,
    warmup_steps: int,
    total_steps: int,
    min_lr_ratio: float = 0.0,
    clock: ScheduleClock | None = None,
) -> torch.optim.lr_scheduler.LambdaLR:
    """A `LambdaLR` following `lr_multiplier`; its state (step count) is saved with the training state.

    With a `clock` (time horizon), each `scheduler.step()` also reads the used fraction of the time budget.
    """
    if schedule not in SCHEDULES:
        raise ValueError(f"optim.schedule must be one of {SCHEDULES}, got {schedule!r}")
    return torch.optim.lr_scheduler.LambdaLR(
        optimizer,
        lambda step: lr_multiplier(
            step, schedule, warmup_steps, total_steps, min_lr_ratio, clock.fraction if clock else 0.0
        ),
    )
