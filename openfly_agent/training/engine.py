"""Model-agnostic assembly of a run: the Accelerator, the seeded train loader, optimizer, schedule, resume.

`training/builder.py` builds the OpenFly-Agent pieces (tokenizer, agent, datasets, collator) and hands them
here; tests can hand in any `nn.Module` whose `forward(batch)` returns `(loss, logs)`.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from pathlib import Path

import torch
from accelerate import Accelerator, PartialState
from accelerate.utils import ProjectConfiguration
from torch.utils.data import DataLoader, Dataset

from openfly_agent.training.checkpoint import CheckpointManager
from openfly_agent.training.config import TrainConfig
from openfly_agent.training.evaluate import make_eval_loader
from openfly_agent.training.loop import TrainingRun
from openfly_agent.training.optim import make_optimizer, make_scheduler
from openfly_agent.training.preflight import check_batch
from openfly_agent.training.sampler import EpochShuffleSampler
from openfly_agent.training.saving import register_state_hooks, restore_checkpoint
from openfly_agent.training.state import TrainerState
from openfly_agent.training.trackers import make_trackers
from openfly_agent.utils.config import config_to_dict

logger = logging.getLogger(__name__)

LOGS_DIR = "logs"


def use_cpu(cfg: TrainConfig) -> bool:
    """CPU when asked for, or when no CUDA device exists.

    accelerate only forms a multi-process CPU group (gloo) when the Accelerator is built with `cpu=True`;
    `accelerate launch --multi_gpu --num_processes N` or torchrun on a CPU machine then trains N processes.
    """
    return cfg.cpu or not torch.cuda.is_available()


def world_size(cfg: TrainConfig) -> int:
    """Processes of this launch (initialises the process group once; no model is built)."""
    return PartialState(cpu=use_cpu(cfg)).num_processes


def make_accelerator(cfg: TrainConfig) -> Accelerator:
    """An Accelerator with the derived gradient accumulation, mixed precision and trackers of `cfg`.

    Raises:
        PreflightError: the global batch does not divide over the processes and per-device batch.
    """
    cpu = use_cpu(cfg)
    accumulation = check_batch(cfg.batch, world_size(cfg))
    output_dir = Path(cfg.output_dir)
    run_name = cfg.logging.run_name or output_dir.name
    accelerator = Accelerator(
        cpu=cpu,
        mixed_precision=cfg.precision,
        gradient_accumulation_steps=accumulation,
        log_with=make_trackers(cfg.logging.tracker, run_name, output_dir / LOGS_DIR),
        project_config=ProjectConfiguration(
            project_dir=str(output_dir), logging_dir=str(output_dir / LOGS_DIR)
        ),
        step_scheduler_with_optimizer=False,  # the schedule is per optimizer step, whatever the world size
    )
    logger.info(
        "accelerator: %s, %d process(es), device %s, precision %s, accumulation %d (global batch %d)",
        accelerator.distributed_type,
        accelerator.num_processes,
        accelerator.device,
        cfg.precision,
        accumulation,
        cfg.batch.global_batch_size,
    )
    return accelerator


def total_steps(cfg: TrainConfig, steps_per_epoch: int) -> int:
    """Optimizer steps of the run: `steps`, else `ceil(epochs x steps_per_epoch)`."""
    if cfg.steps is not None:
        return cfg.steps
    return max(1, math.ceil(cfg.epochs * steps_per_epoch))


def assemble_run(
    cfg: TrainConfig,
    accelerator: Accelerator,
    model: torch.nn.Module,
    train_dataset: Dataset,
    collate_fn: Callable,
    make_export: Callable[[torch.nn.Module], Callable[[Path], None]],
    val_dataset: Dataset | None = None,
    test_dataset: Dataset | None = None,
    resume_from: Path | None = None,
    majority_rate: Callable[[list[int]], float] | None = None,
    after_training: Callable[[TrainingRun], None] | None = None,
) -> TrainingRun:
    """Prepare model, optimizer, schedule and loaders with accelerate, restore a checkpoint, start trackers.

    Args:
        cfg: the run's configuration.
        accelerator: from `make_accelerator`.
        model: the network; `forward(batch) -> (loss, logs)`. Freeze stages / LoRA must already be applied.
        train_dataset: map-style dataset of training samples.
        collate_fn: samples -> batch dict.
        make_export: prepared model -> `export(folder)`, which writes the model's Hugging Face folder into a
            checkpoint folder on every process (see `training/saving.py`).
        val_dataset: periodic validation samples (None: no validation).
        test_dataset: final evaluation samples (None: no final evaluation).
        resume_from: a checkpoint folder to continue from.
        majority_rate: maps the final evaluation's sample indices to the majority-class rate.
        after_training: called on every process after the final checkpoint (e.g. the LoRA merge).
    """
    per_device = cfg.batch.per_device_batch_size
    sampler = EpochShuffleSampler(len(train_dataset), cfg.batch.global_batch_size, cfg.seed)
    train_loader = DataLoader(
        train_dataset,
        batch_size=per_device,
        sampler=sampler,
        drop_last=True,
        collate_fn=collate_fn,
        num_workers=cfg.data.num_workers,
        persistent_workers=False,  # fresh workers each epoch see the dataset's current epoch (random history)
        generator=torch.Generator().manual_seed(cfg.seed),  # keeps the global torch RNG out of data loading
    )
    steps = total_steps(cfg, sampler.steps_per_epoch)
    optimizer = make_optimizer(model, cfg.optim.lr, cfg.optim.weight_decay, cfg.optim.betas, cfg.optim.eps)
    scheduler = make_scheduler(
        optimizer, cfg.optim.schedule, cfg.optim.warmup_steps, steps, cfg.optim.min_lr_ratio
    )
    model, optimizer, train_loader, scheduler = accelerator.prepare(model, optimizer, train_loader, scheduler)
    register_state_hooks(accelerator)
    eval_batch = cfg.validation.per_device_batch_size or per_device
    val_loader = test_loader = None
    test_indices: list[int] = []
    if val_dataset is not None and cfg.validation.interval:
        val_loader, _ = make_eval_loader(
            val_dataset, cfg.validation.max_samples, eval_batch, accelerator, collate_fn, cfg.data.num_workers
        )
    if test_dataset is not None and cfg.validation.final_eval:
        test_loader, test_indices = make_eval_loader(
            test_dataset,
            cfg.validation.final_max_samples,
            eval_batch,
            accelerator,
            collate_fn,
            cfg.data.num_workers,
        )
    state = TrainerState(world_size=accelerator.num_processes)
    if resume_from is not None:
        state = restore_checkpoint(accelerator, resume_from)
    accelerator.init_trackers(cfg.logging.project, config=flat_config(cfg))
    logger.info(
        "run: %d steps (%d per epoch), starting at step %d", steps, sampler.steps_per_epoch, state.step
    )
    return TrainingRun(
        cfg=cfg,
        accelerator=accelerator,
        model=model,
        optimizer=optimizer,
        scheduler=scheduler,
        train_loader=train_loader,
        sampler=sampler,
        val_loader=val_loader,
        test_loader=test_loader,
        state=state,
        total_steps=steps,
        checkpoints=CheckpointManager(cfg.output_dir, cfg.checkpoint.keep_last),
        export=make_export(model),
        majority_rate=(lambda: majority_rate(test_indices)) if majority_rate and test_indices else None,
        after_training=after_training,
    )


def flat_config(cfg: TrainConfig) -> dict[str, str | int | float | bool]:
    """`{"optim.lr": 3e-4, ...}`: the config as flat scalars (what TensorBoard hparams accept)."""
    flat: dict[str, str | int | float | bool] = {}

    def visit(prefix: str, value) -> None:
        if isinstance(value, dict):
            for key, sub in value.items():
                visit(f"{prefix}.{key}" if prefix else key, sub)
        elif isinstance(value, (str, int, float, bool)):
            flat[prefix] = value
        else:
            flat[prefix] = str(value)

    visit("", config_to_dict(cfg))
    return flat
