"""The first part of a training run: `set_up(cfg)` checks the inputs and builds everything the loop works with.

In order: checks before any compute (each failure is a `PreflightError` that says what to change), the agent
and the stage's samples of each split, optimizer, schedule and loaders through accelerate, a resumed state,
the trackers, and the loop's instruments (progress bar, step timer, stop flags). The result is one `Run`.
"""

from __future__ import annotations

import dataclasses
import logging
import math
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from accelerate import Accelerator
from timm.utils import ModelEmaV3
from torch import nn
from torch.utils.data import DataLoader

from openfly_agent.training.accelerator import flat_config, make_accelerator
from openfly_agent.training.best import BestMetric
from openfly_agent.training.builder import load_splits, prepare_agent
from openfly_agent.training.checkpoint import CheckpointManager
from openfly_agent.training.config import TrainConfig
from openfly_agent.training.ema import make_ema
from openfly_agent.training.evaluate import EvalBatches, make_eval_loader
from openfly_agent.training.loaders import epoch_batches, make_train_loader
from openfly_agent.training.memory_estimate import check_memory
from openfly_agent.training.metrics import RunningMeans, ThroughputMeter
from openfly_agent.training.optim import ScheduleClock, make_optimizer, make_scheduler
from openfly_agent.training.preflight import check_dataset_root, check_output_dir, resolve_val_split
from openfly_agent.training.resume_settings import record_run_settings, resume_changes
from openfly_agent.training.saving import register_state_hooks, restore_checkpoint
from openfly_agent.training.stages import StageData, stage_data
from openfly_agent.training.state import TrainerState
from openfly_agent.training.step_timer import StepTimer
from openfly_agent.training.stops import StopFlags, forced_stop_step
from openfly_agent.training.throughput import StepFlops, device_peak_flops
from openfly_agent.training.trackers import start_trackers
from openfly_agent.utils.progress import progress_bar

logger = logging.getLogger(__name__)


@dataclass
class Optimization:
    """The prepared model, optimizer, schedule and train loader, and what the loop reads beside them."""

    model: nn.Module  # the agent as accelerate wrapped it (DDP / FSDP / DeepSpeed)
    optimizer: Any
    scheduler: Any
    train_loader: DataLoader
    steps_per_epoch: int
    total_steps: int
    clock: ScheduleClock | None  # the used part of the time budget (optim.horizon=time), else None
    step_flops: StepFlops
    ema: ModelEmaV3 | None  # the weight average (optim.ema_decay), else None

    @property
    def evaluated(self) -> nn.Module:
        """What validation, the test split and exports see: the weight average when there is one."""
        return self.model if self.ema is None else self.ema.module


@dataclass
class Run:
    """Everything the loop works with; the loop advances `state` and the last checkpoint's fields.

    Attributes:
        stop_after: tests and device checks only (`stops.forced_stop_step`): exit after this step without the
            final save, as a crash would.
        last_checkpoint / saved_step: the last checkpoint written or resumed from, and its step.
    """

    cfg: TrainConfig
    accelerator: Accelerator
    opt: Optimization
    data: StageData
    val_loader: EvalBatches | None
    test_loader: EvalBatches | None
    test_indices: list[int]
    checkpoints: CheckpointManager
    best: BestMetric | None  # the best validation figure so far (checkpoint.keep_best), else None
    state: TrainerState
    stop_after: int | None
    last_checkpoint: Path | None
    saved_step: int | None
    # the loop's instruments
    means: RunningMeans
    meter: ThroughputMeter
    timer: StepTimer
    progress: Any
    stops: StopFlags

    def batches(self) -> Iterable[dict]:
        """The micro-batches left in the current epoch, timed."""
        loader, train_set = self.opt.train_loader, self.data.train
        return self.timer.batches(epoch_batches(loader, train_set, self.state, self.accelerator))


def set_up(cfg: TrainConfig) -> Run:
    """Check the inputs of `cfg` (every process, before any compute), then build the run.

    Raises:
        PreflightError: bad input (output folder, dataset, batch sizes, checkpoints), before any compute.
    """
    stop_after = forced_stop_step()  # tests and device checks only: an environment variable (stops.py)
    cfg, resume_from, setting_changes, val_warning = _checked(cfg)
    accelerator = make_accelerator(cfg)  # processes, precision, accumulation = global / (per device x world)
    # CUDA: the per-GPU estimate; refused here when it cannot fit, before any read
    check_memory(cfg, accelerator)
    checkpoints = CheckpointManager(cfg.output_dir, cfg.checkpoint.keep_last)
    if accelerator.is_main_process:
        checkpoints.remove_stale_staging()
    splits = load_splits(cfg.data, cfg.model.grounding)
    if val_warning:
        logger.warning(val_warning)
    # the agent, whose processor prepares every input, and the stage's samples of each split (navigation:
    # per-step samples with history; grounding: expressions and instruction targets)
    agent = prepare_agent(cfg, splits, accelerator, resume_from)
    data = stage_data(cfg, splits, agent)
    if accelerator.is_main_process:  # train_config.json keeps the first settings; resumes append changes
        record_run_settings(cfg, resume_from, setting_changes)
    opt = _optimization(cfg, agent, data, accelerator)
    val_loader, test_loader, test_indices = _eval_loaders(cfg, data, accelerator)
    state, last_checkpoint = TrainerState(world_size=accelerator.num_processes), None
    if resume_from is not None:
        state, last_checkpoint = _resumed(accelerator, resume_from, opt), resume_from
    # checkpoint.keep_best: the best validation figure so far (read back from `checkpoints/best` on a resume)
    keep_best = cfg.checkpoint.keep_best
    best = BestMetric.resume(keep_best, checkpoints.best()) if keep_best else None
    # a resume first drops what was logged after its checkpoint: those steps are logged again (trackers.py)
    resumed_at = None if resume_from is None else state.step
    start_trackers(accelerator, cfg.logging.project, flat_config(cfg), resumed_at)
    logger.info(
        "run: %d steps (%d per epoch), starting at step %d", opt.total_steps, opt.steps_per_epoch, state.step
    )
    timer = StepTimer(accelerator.device, opt.step_flops, device_peak_flops(accelerator.device))  # time split
    progress = progress_bar(
        total=opt.total_steps, initial=state.step, disable=not accelerator.is_main_process, desc="train"
    )
    opt.model.train()
    stops = StopFlags(accelerator, cfg.time_limit_minutes, elapsed_before_s=state.train_seconds)
    if opt.clock is not None:
        opt.clock.fraction = stops.used_fraction
    return Run(
        cfg, accelerator, opt, data, val_loader, test_loader, test_indices, checkpoints, best, state,
        stop_after=stop_after, last_checkpoint=last_checkpoint, saved_step=resumed_at,
        means=RunningMeans(), meter=ThroughputMeter(), timer=timer, progress=progress, stops=stops,
    )  # fmt: skip


def _checked(cfg: TrainConfig) -> tuple[TrainConfig, Path | None, dict[str, tuple], str | None]:
    """The checks before any compute: `(cfg with its val split, checkpoint to resume, resumed setting changes,
    the val split's warning)`."""
    resume_from = check_output_dir(cfg.output_dir, cfg.resume)
    # the dataset's val split; test_seen (with a warning) on a dataset without one, as the run records it
    data, val_warning = resolve_val_split(cfg.data)
    cfg = dataclasses.replace(cfg, data=data)
    # a resume refuses settings other than its checkpoint's, except RESUMABLE_KEYS (training/resume_settings.py)
    setting_changes = resume_changes(cfg, resume_from)
    check_dataset_root(cfg.data)
    return cfg, resume_from, setting_changes, val_warning


def _optimization(
    cfg: TrainConfig, agent: nn.Module, data: StageData, accelerator: Accelerator
) -> Optimization:
    """Optimizer, schedule and train loader; accelerate wraps them for the launch (DDP / FSDP / DeepSpeed)."""
    train_loader, sampler = make_train_loader(data.train, data.collate, cfg)
    total_steps = cfg.steps or max(1, math.ceil(cfg.epochs * sampler.steps_per_epoch))
    optim = cfg.optim
    fused = optim.fused_adamw and accelerator.device.type == "cuda"  # the fused kernel: CUDA only
    optimizer = make_optimizer(agent, optim.lr, optim.weight_decay, optim.betas, optim.eps, fused=fused)
    step_flops = StepFlops.from_agent(agent)  # the log's model FLOPs: the unwrapped agent, as it trains
    clock = ScheduleClock() if optim.horizon == "time" else None  # the used part of the time budget
    scheduler = make_scheduler(
        optimizer, optim.schedule, optim.warmup_steps, total_steps, optim.min_lr_ratio, clock
    )
    model, optimizer, train_loader, scheduler = accelerator.prepare(agent, optimizer, train_loader, scheduler)
    register_state_hooks(accelerator)  # checkpoints keep trainable tensors only
    ema = make_ema(accelerator, model, optim.ema_decay)
    return Optimization(
        model,
        optimizer,
        scheduler,
        train_loader,
        sampler.steps_per_epoch,
        total_steps,
        clock,
        step_flops,
        ema,
    )


def _eval_loaders(
    cfg: TrainConfig, data: StageData, accelerator: Accelerator
) -> tuple[EvalBatches | None, EvalBatches | None, list[int]]:
    """`(validation loader, test-split loader, the test samples evaluated)`; None where the run has no such
    pass (`validation.interval=0`, `validation.final_eval=false`)."""
    eval_batch = cfg.validation.per_device_batch_size or cfg.batch.per_device_batch_size
    workers = cfg.data.num_workers
    val_loader = test_loader = None
    test_indices: list[int] = []
    if cfg.validation.interval:
        val_loader, _ = make_eval_loader(
            data.val, cfg.validation.max_samples, eval_batch, accelerator, data.collate, workers
        )
    if cfg.validation.final_eval:
        test_loader, test_indices = make_eval_loader(
            data.test, cfg.validation.final_max_samples, eval_batch, accelerator, data.collate, workers
        )
    return val_loader, test_loader, test_indices


def _resumed(accelerator: Accelerator, resume_from: Path, opt: Optimization) -> TrainerState:
    """The state of `resume_from`: optimizer, schedule, RNG and weights restored; its step is saved already."""
    state = restore_checkpoint(accelerator, resume_from, opt.ema)
    if state.step >= opt.total_steps:
        logger.info(
            "nothing left to train: %s is at step %d of the %d configured; no checkpoint is written and its "
            "weights are left as they are",
            resume_from,
            state.step,
            opt.total_steps,
        )
    return state
