"""Resumable training state: `trainer_state.json` counters plus accelerate's optimizer/scheduler/RNG state.

Only trainable tensors go into the accelerate state (frozen weights are rebuilt from the config and the init
checkpoint at start-up), so a LoRA checkpoint of a 7B model stays small.
"""

from __future__ import annotations

import dataclasses
import json
import logging
from collections import OrderedDict
from pathlib import Path

from torch import nn

from openfly_agent.constants import TRAINER_STATE_NAME

logger = logging.getLogger(__name__)

ACCELERATE_STATE_DIR = "training_state"


@dataclasses.dataclass
class TrainerState:
    """Counters that place a run in its data stream; saved with every checkpoint.

    Attributes:
        step: optimizer steps done.
        epoch: the epoch the next batch comes from.
        step_in_epoch: optimizer steps already done in `epoch` (batches to skip on resume).
        samples_seen: training samples consumed (all processes).
        world_size: processes of the run that saved it (the data order is the same at any world size).
        train_seconds: training wall time of the run up to the save, resumes included (the time limit and the
            time horizon of the lr schedule count from it).
    """

    step: int = 0
    epoch: int = 0
    step_in_epoch: int = 0
    samples_seen: int = 0
    world_size: int = 1
    train_seconds: int = 0

    def advance(self, samples: int, steps_per_epoch: int, world_size: int) -> None:
        """Count one optimizer step of `samples` samples; the epoch rolls over after `steps_per_epoch` steps."""
        self.step += 1
        self.step_in_epoch += 1
        self.samples_seen += samples
        self.world_size = world_size
        if self.step_in_epoch >= steps_per_epoch:
            self.epoch += 1
            self.step_in_epoch = 0

    def save(self, folder: str | Path) -> None:
        """Write `trainer_state.json` into `folder`."""
        text = json.dumps(dataclasses.asdict(self), indent=2, sort_keys=True) + "\n"
        (Path(folder) / TRAINER_STATE_NAME).write_text(text)

    @classmethod
    def load(cls, folder: str | Path) -> TrainerState:
        """Read `trainer_state.json` from a checkpoint folder; errors name the file and field."""
        path = Path(folder) / TRAINER_STATE_NAME
        if not path.is_file():
            raise FileNotFoundError(f"{path} is missing: {folder} is not a complete training checkpoint")
        data = json.loads(path.read_text())
        known = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(data) - known)
        if unknown:
            raise ValueError(f"{path}: unknown fields {unknown}")
        for name, value in data.items():
            if not isinstance(value, int) or value < 0:
                raise ValueError(f"{path}: field {name!r} must be a non-negative integer, got {value!r}")
        return cls(**data)


def frozen_parameter_names(model: nn.Module) -> set[str]:
    """Names (as in `model.state_dict()`) of the parameters that do not train."""
    return {name for name, p in model.named_parameters(remove_duplicate=False) if not p.requires_grad}


def keep_trainable_weights_hook(models: list[nn.Module], weights: list[dict], output_dir: str) -> None:
    """accelerate save-state pre-hook: drop frozen parameters from the state dicts it is about to write."""
    for i, (model, state_dict) in enumerate(zip(models, weights)):
        frozen = frozen_parameter_names(model)
        weights[i] = OrderedDict((k, v) for k, v in state_dict.items() if k not in frozen)
        logger.debug(
            "training state: %d of %d tensors kept (frozen ones dropped)", len(weights[i]), len(state_dict)
        )


def load_trainable_weights_hook(models: list[nn.Module], input_dir: str) -> None:
    """accelerate load-state pre-hook: load the trainable tensors ourselves and take the models off the list.

    accelerate would load the file strictly and fail on the missing frozen weights; here the missing keys must
    be exactly frozen parameters, and anything else is an error that names the checkpoint.
    """
    from safetensors.torch import load_file

    for i in range(len(models)):
        model = models.pop(0)
        suffix = "" if i == 0 else f"_{i}"
        path = Path(input_dir) / f"model{suffix}.safetensors"
        if not path.is_file():
            raise FileNotFoundError(f"{path} is missing: the training state in {input_dir} is incomplete")
        device = next(model.parameters()).device
        state_dict = load_file(str(path), device=str(device))
        result = model.load_state_dict(state_dict, strict=False)
        missing = (
            set(result.missing_keys) - frozen_parameter_names(model) - _tied_aliases(model, set(state_dict))
        )
        if result.unexpected_keys or missing:
            raise RuntimeError(
                f"{path} does not match the model being trained: unexpected "
                f"{sorted(result.unexpected_keys)[:5]}, missing trainable {sorted(missing)[:5]}; "
                "the run's config (freeze stage, LoRA) must be the one it was saved with"
            )


def _tied_aliases(model: nn.Module, loaded: set[str]) -> set[str]:
    """Parameter names that share storage with a loaded one (tied weights are written once by accelerate)."""
    groups: dict[int, set[str]] = {}
    for name, p in model.named_parameters(remove_duplicate=False):
        groups.setdefault(p.data_ptr(), set()).add(name)
    return {name for names in groups.values() if names & loaded for name in names}
