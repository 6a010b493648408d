"""Grounding-stage training samples: expression frames of the grounding dataset (data/grounding.py) and
navigation steps seen as (instruction, target box) pairs, mixed in one dataset (training/stages.py)."""

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


class GroundingMixture(torch.utils.data.Dataset):
    """Expression frames and navigation steps (instruction + target box) in one dataset for the grounding stage.

    Indices `[0, E)` are the expression frames; `[E, E + N)` navigation samples, with N chosen so that a
    fraction `instruction_fraction` of the samples are navigation ones. Navigation indices cycle through the
    navigation dataset with an epoch offset, so every epoch sees other steps when N < its length.

    Args:
        expressions: the expression frames (`GroundingFrameDataset`).
        instructions: navigation samples with `instruction`, `rgb`, `box`, `box_visible` (a
            `NavigationStepDataset`), or None for expressions only.
        instruction_fraction: share of navigation samples, in [0, 1).
    """

    def __init__(
        self, expressions: GroundingFrameDataset, instructions=None, instruction_fraction: float = 0.0
    ):
        if not 0.0 <= instruction_fraction < 1.0:
            raise ValueError(f"instruction_fraction={instruction_fraction} must be in [0, 1)")
        self.expressions, self.instructions = expressions, instructions
        size = len(expressions)
        wanted = round(size * instruction_fraction / (1.0 - instruction_fraction))
        self.num_instructions = 0 if instructions is None or not len(instructions) else wanted
        self.epoch = 0

    def __len__(self) -> int:
        return len(self.expressions) + self.num_instructions

    def set_epoch(self, epoch: int) -> None:
        self.epoch = int(epoch)
        self.expressions.set_epoch(epoch)
        if self.instructions is not None and hasattr(self.instructions, "set_epoch"):
            self.instructions.set_epoch(epoch)

    def __getitem__(self, index: int) -> dict:
        if index < len(self.expressions):
            return self.expressions[index]
        offset = (index - len(self.expressions) + self.epoch * self.num_instructions) % len(self.instructions)
        return instruction_sample(self.instructions[offset])


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
