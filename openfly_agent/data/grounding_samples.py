"""Grounding samples: expression frames of the grounding dataset (data/grounding.py) and navigation steps seen
as (instruction, target box) pairs, and the mixture that puts a second kind of sample into a stage's training
data (training/stages.py)."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import torch

from openfly_agent import constants as C
from openfly_agent.data.grounding import GroundingFrame

GROUNDING_KIND = "kind"  # sample key: EXPRESSION_SAMPLE or INSTRUCTION_SAMPLE
EXPRESSION_SAMPLE = "expression"  # a grounding frame with referring expressions
INSTRUCTION_SAMPLE = "instruction"  # a navigation frame with its instruction and the target's box
EXPRESSIONS = "expressions"
BOXES = "boxes"


class GroundingFrameDataset(torch.utils.data.Dataset):
    """One sample per grounding frame: its RGB and `expressions_per_frame` of its expressions with their boxes.

    The expressions of a frame are drawn without replacement (all of them when it has fewer) from a generator
    seeded by (seed, epoch, index), so a sample is reproducible and `set_epoch` shows other expressions.

    Args:
        frames: rows of the grounding dataset (`read_grounding_frames`).
        expressions_per_frame: sequences per frame (the frame is encoded once for all of them).
        seed: seed of the draws.
        target_attributes: (scene id, landmark id) -> (4,) attribute ids; each sample then carries the
            attributes of its expressions' landmarks, (k, 4) (model.grounding.attribute_weight).
    """

    def __init__(
        self,
        frames: list[GroundingFrame],
        expressions_per_frame: int = 4,
        seed: int = 0,
        target_attributes: Callable[[str, str], np.ndarray] | None = None,
    ) -> None:
        if expressions_per_frame < 1:
            raise ValueError(f"expressions_per_frame={expressions_per_frame} must be >= 1")
        self.frames = [f for f in frames if f.expressions]
        self.expressions_per_frame, self.seed, self.epoch = expressions_per_frame, seed, 0
        self.target_attributes = target_attributes

    def __len__(self) -> int:
        return len(self.frames)

    def set_epoch(self, epoch: int) -> None:
        """Draw other expressions of each frame (call once per epoch)."""
        self.epoch = int(epoch)

    def __getitem__(self, index: int) -> dict:
        frame = self.frames[index]
        rng = np.random.default_rng([self.seed, self.epoch, index])
        count = min(self.expressions_per_frame, len(frame.expressions))
        picks = np.sort(rng.choice(len(frame.expressions), size=count, replace=False))
        sample = {
            GROUNDING_KIND: EXPRESSION_SAMPLE,
            C.OBS_RGB: frame.rgb(),
            EXPRESSIONS: [frame.expressions[k] for k in picks],
            BOXES: frame.boxes[picks].astype(np.float32),  # (k, 4), all visible
        }
        if self.target_attributes is not None:
            every = np.stack(
                [self.target_attributes(frame.scene_id, key) for key in frame.landmark_ids]
            )  # (E, 4)
            sample[C.TARGET_ATTRIBUTES] = every[picks]  # (k, 4)
        return sample


class DatasetMixture(torch.utils.data.Dataset):
    """Two datasets in one, for a stage that trains on a second kind of sample beside its own.

    Indices `[0, M)` are `main`'s samples; `[M, M + N)` are `extra`'s, with N chosen so that a fraction
    `extra_fraction` of the samples are extra ones. Extra indices cycle through `extra` with an epoch offset, so
    every epoch sees other extra samples when N < its length. The grounding stage mixes navigation targets
    (`InstructionTargets`) into its expression frames (`data.instruction_fraction`); the navigation stage mixes
    expression frames into its steps (`data.expression_fraction`).

    Args:
        main: the stage's own samples.
        extra: the other kind, or None (then the mixture is `main`).
        extra_fraction: share of extra samples, in [0, 1).
    """

    def __init__(self, main, extra=None, extra_fraction: float = 0.0):
        if not 0.0 <= extra_fraction < 1.0:
            raise ValueError(f"extra_fraction={extra_fraction} must be in [0, 1)")
        self.main, self.extra = main, extra
        size = len(main)
        wanted = round(size * extra_fraction / (1.0 - extra_fraction))
        self.num_extra = 0 if extra is None or not len(extra) else wanted
        self.epoch = 0

    def __len__(self) -> int:
        return len(self.main) + self.num_extra

    def set_epoch(self, epoch: int) -> None:
        self.epoch = int(epoch)
        for part in (self.main, self.extra):
            if part is not None and hasattr(part, "set_epoch"):
                part.set_epoch(epoch)

    def __getitem__(self, index: int) -> dict:
        if index < len(self.main):
            return self.main[index]
        offset = (index - len(self.main) + self.epoch * self.num_extra) % len(self.extra)
        return self.extra[offset]


class InstructionTargets(torch.utils.data.Dataset):
    """A navigation split seen as grounding samples: each step's frame, instruction and target box."""

    def __init__(self, steps) -> None:
        self.steps = steps

    def __len__(self) -> int:
        return len(self.steps)

    def set_epoch(self, epoch: int) -> None:
        if hasattr(self.steps, "set_epoch"):
            self.steps.set_epoch(epoch)

    def __getitem__(self, index: int) -> dict:
        return instruction_sample(self.steps[index])


def instruction_sample(step: dict) -> dict:
    """A navigation step as a grounding sample: the instruction and the target's box (no memory, no action), and
    the target's attributes when the step has them."""
    sample = {
        GROUNDING_KIND: INSTRUCTION_SAMPLE,
        C.OBS_RGB: step[C.OBS_RGB],
        C.OBS_INSTRUCTION: step[C.OBS_INSTRUCTION],
        C.BOX: np.asarray(step[C.BOX], dtype=np.float32),
        C.BOX_VISIBLE: bool(step[C.BOX_VISIBLE]),
    }
    if C.TARGET_ATTRIBUTES in step:
        sample[C.TARGET_ATTRIBUTES] = step[C.TARGET_ATTRIBUTES]
    return sample
