"""Batch dataset samples into the training contract of docs/INTERFACES.md (keys from constants.py).

The tokenizer, action tokenizer, image transform and prompt builder are injected (they belong to the
model), so this module knows nothing about a particular LLM or action head.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence
from typing import Protocol

import numpy as np
import torch

from openfly_agent import constants as C

logger = logging.getLogger(__name__)


class ActionTokenizer(Protocol):
    """What the collator needs from model/action_tokenizer.py."""

    def action_to_token_ids(self, action_id: int) -> list[int]: ...


class NavigationCollator:
    """Tokenise prompts and actions, stack frames and memory sets, build labels and masks.

    `input_ids` = tokenizer(prompt_builder(instruction)) (with its special tokens; BOS is prepended if
    the tokenizer has one and did not add it), then `action_tokenizer.action_to_token_ids(action)`, then
    EOS when `append_eos`. Labels are IGNORE_INDEX except on the action tokens (and that EOS). Sequences
    are right padded. When `max_length` is set, prompts are cut from the end so the action tokens always
    fit. Memory sets fill (K, S) slots from the front (set 0 = oldest); empty slots are zeros with mask
    False. Invisible boxes are zeros with visibility False.

    Args:
        tokenizer: a Hugging Face tokenizer (callable, `bos_token_id`, `eos_token_id`, `pad_token_id`).
        action_tokenizer: has `action_to_token_ids(action_id) -> list[int]`.
        image_transform: rgb (H, W, 3) uint8 -> (3, h, w) uint8 tensor at the model's input size.
        prompt_builder: instruction -> prompt text.
        capacity: K, memory sets per sample.
        set_size: S, frames per set.
        max_length: longest `input_ids` allowed, or None.
        append_eos: supervise an EOS after the action tokens (the `openvla_bins` head does).
        with_metadata: also return EPISODE_ID (list[str]) and STEP_INDEX ((B,) long).
    """

    def __init__(
        self,
        tokenizer,
        action_tokenizer: ActionTokenizer,
        image_transform: Callable[[np.ndarray], torch.Tensor],
        prompt_builder: Callable[[str], str],
        capacity: int,
        set_size: int,
        max_length: int | None = None,
        append_eos: bool = False,
        with_metadata: bool = False,
    ):
        if capacity < 0 or set_size < 1:
            raise ValueError(
                f"capacity={capacity}, set_size={set_size}: need capacity >= 0 and set_size >= 1"
            )
        if append_eos and tokenizer.eos_token_id is None:
            raise ValueError("append_eos=True but the tokenizer has no eos_token_id")
        self.tokenizer, self.action_tokenizer = tokenizer, action_tokenizer
        self.image_transform, self.prompt_builder = image_transform, prompt_builder
        self.capacity, self.set_size, self.max_length = capacity, set_size, max_length
        self.append_eos, self.with_metadata = append_eos, with_metadata
        pad = tokenizer.pad_token_id
        self.pad_id = pad if pad is not None else (tokenizer.eos_token_id or 0)

    def tokenize(self, instruction: str, action: int) -> tuple[list[int], list[int]]:
        """(input_ids, labels) of one sample, before padding."""
        prompt = list(self.tokenizer(self.prompt_builder(instruction), add_special_tokens=True)["input_ids"])
        bos = self.tokenizer.bos_token_id
        if bos is not None and (not prompt or prompt[0] != bos):
            prompt = [bos, *prompt]
        target = [int(i) for i in self.action_tokenizer.action_to_token_ids(int(action))]
        if self.append_eos:
            target.append(int(self.tokenizer.eos_token_id))
        if self.max_length is not None and len(prompt) + len(target) > self.max_length:
            keep = self.max_length - len(target)
            if keep < 1:
                raise ValueError(
                    f"max_length={self.max_length} leaves no room for {len(target)} action tokens"
                )
            prompt = prompt[:keep]
        return prompt + target, [C.IGNORE_INDEX] * len(prompt) + target

    def _image(self, rgb: np.ndarray) -> torch.Tensor:
        image = self.image_transform(rgb)
        if (
            not isinstance(image, torch.Tensor)
            or image.dtype != torch.uint8
            or image.ndim != 3
            or image.shape[0] != 3
        ):
            got = f"{type(image).__name__} {getattr(image, 'dtype', '')} {tuple(getattr(image, 'shape', ()))}"
            raise ValueError(f"image_transform must return a (3, h, w) uint8 tensor, got {got}")
        return image

    def _text(self, samples: Sequence[dict]) -> dict[str, torch.Tensor]:
        pairs = [self.tokenize(s[C.OBS_INSTRUCTION], s[C.ACTION]) for s in samples]
        length = max(len(ids) for ids, _ in pairs)
        input_ids = torch.full((len(samples), length), self.pad_id, dtype=torch.long)  # (B, L)
        labels = torch.full((len(samples), length), C.IGNORE_INDEX, dtype=torch.long)  # (B, L)
        attention = torch.zeros((len(samples), length), dtype=torch.long)  # (B, L)
        for b, (ids, lab) in enumerate(pairs):
            input_ids[b, : len(ids)] = torch.tensor(ids)
            labels[b, : len(lab)] = torch.tensor(lab)
            attention[b, : len(ids)] = 1
        return {C.INPUT_IDS: input_ids, C.ATTENTION_MASK: attention, C.LABELS: labels}

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
        current = torch.stack([self._image(s[C.OBS_RGB]) for s in samples])  # (B, 3, H, W)
        visible = torch.tensor([bool(s[C.BOX_VISIBLE]) for s in samples], dtype=torch.bool)  # (B,)
        boxes = torch.stack(
            [torch.as_tensor(np.asarray(s[C.BOX], dtype=np.float32)) for s in samples]
        )  # (B, 4)
        batch = {
            **self._text(samples),
            C.PIXEL_VALUES: current,
            **self._memory(samples, tuple(current.shape[1:])),
            C.BOX: torch.where(visible[:, None], boxes, torch.zeros_like(boxes)),
            C.BOX_VISIBLE: visible,
            C.ACTION: torch.tensor([int(s[C.ACTION]) for s in samples], dtype=torch.long),
        }
        if self.with_metadata:
            batch[C.EPISODE_ID] = [s[C.EPISODE_ID] for s in samples]
            batch[C.STEP_INDEX] = torch.tensor([int(s[C.STEP_INDEX]) for s in samples], dtype=torch.long)
        return batch
