"""Batch dataset samples into the training contract of docs/INTERFACES.md (keys from constants.py).

The processor (model/processor.py's `OpenFlyProcessor`) is injected: it turns prompts, action targets and
frames into model inputs, the same way for training and inference, so this module knows nothing about a
particular LLM, image size or action head.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping, Sequence
from typing import Protocol

import numpy as np
import torch

from openfly_agent import constants as C
from openfly_agent.data.grounding_samples import BOXES, EXPRESSION_SAMPLE, EXPRESSIONS, GROUNDING_KIND

logger = logging.getLogger(__name__)


class InputProcessor(Protocol):
    """What the collator needs from model/processor.py's `OpenFlyProcessor`."""

    def navigation_prompt(self, instruction: str) -> str:
        """The text after the visual tokens for an instruction."""
        ...

    def image(self, rgb: np.ndarray) -> torch.Tensor:
        """(H, W, 3) uint8 RGB -> (3, h, w) uint8 at the model's input size."""
        ...

    def __call__(self, text: list[str], images: list[np.ndarray], actions: list[int]) -> Mapping:
        """Prompts, current frames and action targets -> input_ids, attention_mask, labels, pixel_values."""
        ...


class NavigationCollator:
    """Samples of `NavigationStepDataset` -> a training batch, through the model's processor.

    Text and the current frame come from `processor(prompts, frames, actions)` (right-padded `input_ids`,
    `attention_mask`, `labels` that are IGNORE_INDEX except on the action tokens, `pixel_values`); memory
    frames from `processor.image`. Memory sets fill (K, S) slots from the front (set 0 = oldest); empty slots are
    zeros with mask False. Invisible boxes are zeros with visibility False.

    Args:
        processor: prepares model inputs (`InputProcessor`: the agent's `OpenFlyProcessor`).
        capacity: K, memory sets per sample (the model's `memory.capacity`).
        set_size: S, frames per set (the model's keyframe set size).
        with_metadata: also return EPISODE_ID (list[str]) and STEP_INDEX ((B,) long).
    """

    def __init__(self, processor: InputProcessor, capacity: int, set_size: int, with_metadata: bool = False):
        if capacity < 0 or set_size < 1:
            raise ValueError(
                f"capacity={capacity}, set_size={set_size}: need capacity >= 0 and set_size >= 1"
            )
        self.processor = processor
        self.capacity, self.set_size = capacity, set_size
        self.with_metadata = with_metadata

    def _image(self, rgb: np.ndarray) -> torch.Tensor:
        image = self.processor.image(rgb)
        if (
            not isinstance(image, torch.Tensor)
            or image.dtype != torch.uint8
            or image.ndim != 3
            or image.shape[0] != 3
        ):
            got = f"{type(image).__name__} {getattr(image, 'dtype', '')} {tuple(getattr(image, 'shape', ()))}"
            raise ValueError(f"the processor's image() must return a (3, h, w) uint8 tensor, got {got}")
        return image

    def _memory(self, samples: Sequence[dict], image_shape: tuple[int, ...]) -> dict[str, torch.Tensor]:
        b, k, s = len(samples), self.capacity, self.set_size
        pixels = torch.zeros((b, k, s, *image_shape), dtype=torch.uint8)  # (B, K, S, 3, H, W)
        mask = torch.zeros((b, k, s), dtype=torch.bool)  # (B, K, S)
        boxes = torch.zeros((b, k, s, 4), dtype=torch.float32)  # (B, K, S, 4)
        visible = torch.zeros((b, k, s), dtype=torch.bool)  # (B, K, S)
        for i, sample in enumerate(samples):
            sets = sample[C.MEMORY][-k:] if k else []
            for j, frame_set in enumerate(sets):
                for f, (rgb, box, vis) in enumerate(frame_set[-s:]):
                    pixels[i, j, f] = self._image(rgb)
                    mask[i, j, f] = True
                    visible[i, j, f] = bool(vis)
                    if vis:
                        boxes[i, j, f] = torch.as_tensor(np.asarray(box, dtype=np.float32))
        return {
            C.MEMORY_PIXEL_VALUES: pixels,
            C.MEMORY_FRAME_MASK: mask,
            C.MEMORY_BOXES: boxes,
            C.MEMORY_BOX_VISIBLE: visible,
        }

    def __call__(self, samples: Sequence[dict]) -> dict[str, torch.Tensor]:
        """Samples of NavigationStepDataset -> the batch dict (keys and shapes of docs/INTERFACES.md)."""
        if not samples:
            raise ValueError("cannot collate an empty list of samples")
        inputs = self.processor(
            [self.processor.navigation_prompt(s[C.OBS_INSTRUCTION]) for s in samples],
            [s[C.OBS_RGB] for s in samples],
            [int(s[C.ACTION]) for s in samples],
        )  # input_ids, attention_mask, labels (B, L); pixel_values (B, 3, H, W)
        current = inputs[C.PIXEL_VALUES]
        visible = torch.tensor([bool(s[C.BOX_VISIBLE]) for s in samples], dtype=torch.bool)  # (B,)
        boxes = torch.stack(
            [torch.as_tensor(np.asarray(s[C.BOX], dtype=np.float32)) for s in samples]
        )  # (B, 4)
        batch = {
            C.INPUT_IDS: inputs[C.INPUT_IDS],
            C.ATTENTION_MASK: inputs[C.ATTENTION_MASK],
            C.LABELS: inputs[C.LABELS],
            C.PIXEL_VALUES: current,
            **self._memory(samples, tuple(current.shape[1:])),
            C.BOX: torch.where(visible[:, None], boxes, torch.zeros_like(boxes)),
            C.BOX_VISIBLE: visible,
            C.ACTION: torch.tensor([int(s[C.ACTION]) for s in samples], dtype=torch.long),
        }
        if all(C.TARGET_ATTRIBUTES in s for s in samples):
            batch[C.TARGET_ATTRIBUTES] = torch.as_tensor(
                np.stack([s[C.TARGET_ATTRIBUTES] for s in samples]), dtype=torch.long
            )  # (B, 4)
        if self.with_metadata:
            batch[C.EPISODE_ID] = [s[C.EPISODE_ID] for s in samples]
            batch[C.STEP_INDEX] = torch.tensor([int(s[C.STEP_INDEX]) for s in samples], dtype=torch.long)
        return batch


class GroundingCollator:
    """Grounding-stage samples (data/grounding.py) -> a batch with no action targets.

    An expression sample gives one sequence per expression (`processor.grounding_prompt`) that all read its frame;
    an instruction sample one sequence (`processor.navigation_prompt`) with the target's box (maybe not
    visible). Each frame is encoded once: `pixel_values` (F, 3, H, W) and `frame_index` (B,) of each sequence.

    Args:
        processor: prepares model inputs (the agent's `OpenFlyProcessor`: `grounding_prompt`, `navigation_prompt`,
            `image`, and `__call__(prompts)` for the text).
    """

    def __init__(self, processor) -> None:
        self.processor = processor

    def __call__(self, samples: Sequence[dict]) -> dict[str, torch.Tensor]:
        if not samples:
            raise ValueError("cannot collate an empty list of samples")
        prompts, boxes, visible, frame_index, attributes = [], [], [], [], []
        # a sequence without attributes gets -1 ids, which the attribute loss skips
        unknown = np.full(4, -1, dtype=np.int64)
        for frame, sample in enumerate(samples):
            if sample[GROUNDING_KIND] == EXPRESSION_SAMPLE:
                count = len(sample[EXPRESSIONS])
                attributes.extend(sample.get(C.TARGET_ATTRIBUTES, [unknown] * count))
                for expression, box in zip(sample[EXPRESSIONS], sample[BOXES]):
                    prompts.append(self.processor.grounding_prompt(expression))
                    boxes.append(np.asarray(box, dtype=np.float32))
                    visible.append(True)
                    frame_index.append(frame)
            else:
                attributes.append(sample.get(C.TARGET_ATTRIBUTES, unknown))
                prompts.append(self.processor.navigation_prompt(sample[C.OBS_INSTRUCTION]))
                shown = bool(sample[C.BOX_VISIBLE])
                boxes.append(
                    np.asarray(sample[C.BOX], dtype=np.float32) if shown else np.zeros(4, np.float32)
                )
                visible.append(shown)
                frame_index.append(frame)
        text = self.processor(prompts)  # input_ids, attention_mask (B, L); no labels: nothing to supervise
        batch = {
            C.INPUT_IDS: text[C.INPUT_IDS],
            C.ATTENTION_MASK: text[C.ATTENTION_MASK],
            C.PIXEL_VALUES: torch.stack(
                [self.processor.image(s[C.OBS_RGB]) for s in samples]
            ),  # (F, 3, H, W)
            C.FRAME_INDEX: torch.tensor(frame_index, dtype=torch.long),  # (B,)
            C.BOX: torch.from_numpy(np.stack(boxes)),  # (B, 4)
            C.BOX_VISIBLE: torch.tensor(visible, dtype=torch.bool),  # (B,)
        }
        if any(C.TARGET_ATTRIBUTES in s for s in samples):
            batch[C.TARGET_ATTRIBUTES] = torch.as_tensor(np.stack(attributes), dtype=torch.long)  # (B, 4)
        return batch
