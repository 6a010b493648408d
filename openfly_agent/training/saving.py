"""Save and restore a whole checkpoint across processes: HF model folder + accelerate state + counters.

Order of a save: rank 0 creates `.tmp-step-N/`; every process writes its part of the accelerate state and
joins the state-dict gather of the model export; rank 0 writes the counters, then renames the folder and moves
the `last` pointer (and `best`, for the best validation pass so far). A crash before the rename leaves the
previous checkpoint as the newest.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path

from accelerate import Accelerator
from accelerate.utils import DistributedType
from timm.utils import ModelEmaV3
from torch import nn

from openfly_agent.training.best import BEST_RECORD_NAME, BestMetric
from openfly_agent.training.checkpoint import CheckpointManager
from openfly_agent.training.config import TrainConfig
from openfly_agent.training.ema import load_ema, save_ema
from openfly_agent.training.export import export_model_folder
from openfly_agent.training.state import (
    ACCELERATE_STATE_DIR,
    TrainerState,
    keep_trainable_weights_hook,
    load_trainable_weights_hook,
)

logger = logging.getLogger(__name__)


def register_state_hooks(accelerator: Accelerator) -> None:
    """Keep only trainable tensors in the accelerate state (plain and DDP runs).

    FSDP and DeepSpeed save their own sharded model state, which the hooks do not see; there the whole model
    goes into the training state.
    """
    if accelerator.distributed_type in (DistributedType.FSDP, DistributedType.DEEPSPEED):
        return
    accelerator.register_save_state_pre_hook(keep_trainable_weights_hook)
    accelerator.register_load_state_pre_hook(load_trainable_weights_hook)


def save_checkpoint(
    accelerator: Accelerator,
    model: nn.Module,
    state: TrainerState,
    checkpoints: CheckpointManager,
    cfg: TrainConfig,
    ema: ModelEmaV3 | None = None,
    best: BestMetric | None = None,
) -> Path:
    """Write the checkpoint of `state.step` atomically (call on every process); return its folder.

    With a weight average (`ema`), the model folder holds the average, and the training state holds it too
    (`ema.safetensors`, for resuming) next to the live weights. With `best` (this step's validation pass is the
    best so far), the checkpoint keeps its record and `checkpoints/best` names it once it is committed.
    """
    step = state.step
    if accelerator.is_main_process:
        checkpoints.begin(step)
    accelerator.wait_for_everyone()
    staging = checkpoints.staging_dir(step)
    accelerator.save_state(str(staging / ACCELERATE_STATE_DIR))
    export_model_folder(accelerator, model if ema is None else ema.module, staging, cfg)
    if accelerator.is_main_process:
        state.save(staging)
        if ema is not None:
            save_ema(ema, staging / ACCELERATE_STATE_DIR)
        if best is not None:
            (staging / BEST_RECORD_NAME).write_text(json.dumps(best.record(), indent=2) + "\n")
    accelerator.wait_for_everyone()
    if accelerator.is_main_process:
        checkpoints.commit(step)
        if best is not None:
            checkpoints.mark_best(step)
    accelerator.wait_for_everyone()
    return checkpoints.final_dir(step)


def restore_checkpoint(
    accelerator: Accelerator, folder: str | Path, ema: ModelEmaV3 | None = None
) -> TrainerState:
    """Load optimizer, scheduler, RNG, trainable weights (and the weight average, with `ema`) from `folder`
    (every process); return counters.

    Call after `accelerator.prepare` and before the first step.
    """
    folder = Path(folder)
    state = TrainerState.load(folder)
    if state.world_size != accelerator.num_processes:
        raise RuntimeError(
            f"{folder} was saved by {state.world_size} processes but this run has "
            f"{accelerator.num_processes}: resume with the same number of processes "
            "(the per-process RNG and optimizer shards must match)"
        )
    accelerator.load_state(str(folder / ACCELERATE_STATE_DIR))
    if ema is not None:
        load_ema(ema, folder / ACCELERATE_STATE_DIR)
    logger.info(
        "resumed from %s at step %d (epoch %d, step %d of it)",
        folder,
        state.step,
        state.epoch,
        state.step_in_epoch,
    )
    return state
