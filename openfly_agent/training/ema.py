"""An exponential moving average of the agent's weights (`optim.ema_decay`), kept with timm's `ModelEmaV3`.

With an average, validation, the final test evaluation, every checkpoint's model folder (what evaluation, the
next stage's `init` and the Hub release read) and a LoRA merge use the averaged weights; the optimizer keeps
training the live ones, which the checkpoint's training state holds for `--resume`; the average is saved there
too, as `ema.safetensors` (safetensors, as every weight file we read back).

The decay warms up as in timm: min(ema_decay, 1 - (1 + step) ** -0.75), so the first steps do not drag the
random init along (0.9 at step 20, 0.99 at step 460, 0.999 at step 10,000).
"""

from __future__ import annotations

import logging
from pathlib import Path

from accelerate import Accelerator
from accelerate.utils import DistributedType
from safetensors.torch import load_file, load_model, save_model
from timm.utils import ModelEmaV3
from torch import nn

from openfly_agent.constants import WEIGHTS_NAME
from openfly_agent.training.state import ACCELERATE_STATE_DIR

logger = logging.getLogger(__name__)

EMA_WEIGHTS_NAME = "ema.safetensors"
EMA_WARMUP_POWER = 0.75  # timm's advice for runs of about 10k-200k steps


def make_ema(accelerator: Accelerator, model: nn.Module, decay: float | None) -> ModelEmaV3 | None:
    """The average of `model`'s weights (after `accelerator.prepare`), or None when `decay` is None.

    Raises:
        ValueError: under FSDP or DeepSpeed, whose sharded parameters a full copy on each process cannot follow.
    """
    if decay is None:
        return None
    if accelerator.distributed_type in (DistributedType.FSDP, DistributedType.DEEPSPEED):
        raise ValueError(
            f"optim.ema_decay={decay} needs every parameter on every process; it does not work with "
            f"{accelerator.distributed_type.value}: set optim.ema_decay=null"
        )
    agent = accelerator.unwrap_model(model)
    ema = ModelEmaV3(agent, decay=decay, use_warmup=True, warmup_power=EMA_WARMUP_POWER)
    ema.requires_grad_(False)
    logger.info("weight average: decay %s (warmed up), on %s", decay, accelerator.device)
    return ema


def update_ema(ema: ModelEmaV3, accelerator: Accelerator, model: nn.Module, step: int) -> None:
    """Move the average toward the live weights after optimizer step `step` (1-based)."""
    ema.update(accelerator.unwrap_model(model), step=step)


def save_ema(ema: ModelEmaV3, folder: str | Path) -> Path:
    """Write the average's weights (tied tensors once) to `<folder>/ema.safetensors`; return the file."""
    path = Path(folder) / EMA_WEIGHTS_NAME
    save_model(ema.module, str(path))
    return path


def load_ema(ema: ModelEmaV3, folder: str | Path) -> None:
    """Restore the average from a checkpoint `folder`.

    Raises:
        FileNotFoundError: the checkpoint was written without an average (a run without `optim.ema_decay`).
    """
    path = Path(folder) / EMA_WEIGHTS_NAME
    if not path.is_file():
        raise FileNotFoundError(
            f"{path} is missing: the checkpoint was saved without optim.ema_decay; resume with the same setting"
        )
    load_model(ema.module, str(path), strict=True)
    logger.info("weight average restored from %s", path)


def load_live_weights(agent: nn.Module, checkpoint: str | Path) -> int:
    """Put the live (trained) weights of `checkpoint`'s training state into `agent`, loaded from its model folder:
    with `optim.ema_decay` that folder holds the average, and this scores the weights the average followed.

    The training state keeps trainable tensors only; the frozen ones stay as loaded (the average of a constant is
    the constant). Returns the number of tensors replaced.

    Raises:
        FileNotFoundError: the checkpoint has no training state.
        ValueError: the training state names tensors the agent does not have.
    """
    path = Path(checkpoint) / ACCELERATE_STATE_DIR / WEIGHTS_NAME  # accelerate's name for the (first) model
    if not path.is_file():
        raise FileNotFoundError(f"{path} is missing: {checkpoint} has no training state")
    live = load_file(str(path))
    result = agent.load_state_dict(live, strict=False)
    if result.unexpected_keys:
        raise ValueError(f"{path}: tensors the agent does not have: {sorted(result.unexpected_keys)[:5]}")
    logger.info("live weights: %d tensors from %s", len(live), path)
    return len(live)
