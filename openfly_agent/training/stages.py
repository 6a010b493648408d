"""What each training stage reads: its train / validation / test datasets and the collator that batches them.

- `navigation` (the default): per-step samples with history (data/dataset.py), action and grounding targets.
- `grounding`: the alignment stage. Referring expressions of the grounding dataset (`data.grounding_root`) mixed
  with navigation steps seen as (instruction, target box) pairs; validation and test are the navigation splits'
  instruction targets, so its box IoU is the one the navigation stage starts from. No action loss.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

from torch.utils.data import Dataset

from openfly_agent import constants as C
from openfly_agent.data.collator import GroundingCollator, NavigationCollator
from openfly_agent.data.dataset import NavigationStepDataset
from openfly_agent.data.grounding import read_grounding_frames
from openfly_agent.data.grounding_samples import GroundingFrameDataset, GroundingMixture, instruction_sample
from openfly_agent.model.agent import OpenFlyAgent
from openfly_agent.training.config import STAGE_GROUNDING, TrainConfig
from openfly_agent.training.preflight import PreflightError


@dataclass
class StageData:
    """The datasets and the collator of a stage."""

    train: Dataset
    val: Dataset
    test: Dataset
    collate: Callable


class InstructionTargets(Dataset):
    """A navigation split seen as grounding samples: each step's frame, instruction and target box."""

    def __init__(self, steps: NavigationStepDataset) -> None:
        self.steps = steps

    def __len__(self) -> int:
        return len(self.steps)

    def set_epoch(self, epoch: int) -> None:
        self.steps.set_epoch(epoch)

    def __getitem__(self, index: int) -> dict:
        return instruction_sample(self.steps[index])


def stage_data(cfg: TrainConfig, splits, agent: OpenFlyAgent) -> StageData:
    """The datasets of `cfg.stage` over the loaded `splits` (training/builder.py), batched by the agent's processor.

    Raises:
        PreflightError: the grounding stage without `data.grounding_root`, or a root without train frames.
    """
    data = cfg.data
    if cfg.stage != STAGE_GROUNDING:
        return StageData(
            train=splits.dataset(C.SPLIT_TRAIN, cfg, agent),
            val=splits.dataset(data.val_split, cfg, agent),
            test=splits.dataset(data.test_split, cfg, agent),
            collate=NavigationCollator(
                agent.processor, cfg.model.memory.capacity, cfg.model.keyframes.set_size
            ),
        )
    if not data.grounding_root:
        raise PreflightError(
            "stage=grounding needs --data.grounding_root (python -m openfly_agent.toolchain grounding writes it)"
        )
    try:
        frames = read_grounding_frames(data.grounding_root, (C.SPLIT_TRAIN,))
    except FileNotFoundError as err:
        raise PreflightError(str(err)) from err
    if not frames:
        raise PreflightError(f"data.grounding_root {data.grounding_root} has no frames of the train split")
    expressions = GroundingFrameDataset(
        frames,
        data.expressions_per_frame,
        seed=cfg.seed,
        target_attributes=splits.attributes,
    )
    targets = {
        split: InstructionTargets(splits.dataset(split, cfg, agent, history="none"))
        for split in dict.fromkeys((C.SPLIT_TRAIN, data.val_split, data.test_split))
    }
    return StageData(
        train=GroundingMixture(expressions, targets[C.SPLIT_TRAIN], data.instruction_fraction),
        val=targets[data.val_split],
        test=targets[data.test_split],
        collate=GroundingCollator(agent.processor),
    )
