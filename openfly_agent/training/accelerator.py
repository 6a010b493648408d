"""The run's `accelerate.Accelerator`: processes, device, mixed precision, gradient accumulation, trackers."""

from __future__ import annotations

import logging
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import torch
from accelerate import Accelerator, PartialState
from accelerate.utils import DistributedDataParallelKwargs, ProjectConfiguration

from openfly_agent.training.config import STAGE_GROUNDING, TrainConfig
from openfly_agent.training.preflight import check_batch
from openfly_agent.training.trackers import make_trackers
from openfly_agent.utils.config import config_to_dict

logger = logging.getLogger(__name__)

LOGS_DIR = "logs"


def use_cpu(cpu: bool) -> bool:
    """CPU when asked for (`TrainConfig.cpu`), or when no CUDA device exists.

    accelerate only forms a multi-process CPU group (gloo) when the Accelerator is built with `cpu=True`;
    `accelerate launch --multi_gpu --num_processes N` or torchrun on a CPU machine then trains N processes.
    """
    return cpu or not torch.cuda.is_available()


def world_size(cpu: bool) -> int:
    """Processes of this launch (initialises the process group once; no model is built)."""
    return PartialState(cpu=use_cpu(cpu)).num_processes


def make_accelerator(cfg: TrainConfig) -> Accelerator:
    """An Accelerator with the derived gradient accumulation, mixed precision and trackers of `cfg`.

    Raises:
        PreflightError: the global batch does not divide over the processes and per-device batch.
    """
    accumulation = check_batch(cfg.batch, world_size(cfg.cpu))
    output_dir = Path(cfg.output_dir)
    run_name = output_dir.name  # the run's name in its trackers
    accelerator = Accelerator(
        cpu=use_cpu(cfg.cpu),
        mixed_precision=cfg.precision,
        gradient_accumulation_steps=accumulation,
        log_with=make_trackers(cfg.logging.tracker, run_name, output_dir / LOGS_DIR, cfg.logging.project),
        project_config=ProjectConfiguration(
            project_dir=str(output_dir), logging_dir=str(output_dir / LOGS_DIR)
        ),
        step_scheduler_with_optimizer=False,  # the schedule is per optimizer step, whatever the world size
        # the grounding stage has no action target: the LM head and the box token get no gradient there
        kwargs_handlers=[DistributedDataParallelKwargs(find_unused_parameters=cfg.stage == STAGE_GROUNDING)],
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


@contextmanager
def closing_trackers(accelerator: Accelerator) -> Iterator[None]:
    """`with closing_trackers(accelerator):` the trackers are closed (TensorBoard / W&B flushed) on leaving the
    block, whichever way: the end of the run, an early return, an error.

    Not `accelerator.end_training()`: that also destroys the process group while the prepared model is alive,
    which leaves DDP's Reducer as the group's last holder and can deadlock the rank at exit. The entry point
    closes the group once the run is released (`utils.distributed.close_process_group`).
    """
    try:
        yield
    finally:
        for tracker in accelerator.trackers:
            tracker.finish()


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
