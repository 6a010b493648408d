"""Grounding-stage samples: expression frames, the mixture with instruction targets, and their batches."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from openfly_agent import constants as C
from openfly_agent.data.collator import GroundingCollator
from openfly_agent.data.grounding import GroundingFrame
from openfly_agent.data.grounding_samples import (
    BOXES,
    EXPRESSION_SAMPLE,
    EXPRESSIONS,
    GROUNDING_KIND,
    INSTRUCTION_SAMPLE,
    GroundingFrameDataset,
    GroundingMixture,
)


def _frame(index: int, count: int) -> GroundingFrame:
    rgb = np.full((8, 8, 3), index, dtype=np.uint8)
    ok, png = cv2.imencode(".png", rgb)
    assert ok
    boxes = np.array([[0.1 * (k + 1), 0.5, 0.1, 0.2] for k in range(count)], dtype=np.float32)
    return GroundingFrame(
        frame_id=f"f{index}", scene_id="embedded-0", split="train", source_episode="e", pose=(0, 0, 0, 0),
        pitch_deg=-45.0, landmark_ids=[f"lm{k}" for k in range(count)],
        expressions=[f"the building number {k}" for k in range(count)], boxes=boxes, relations=[""] * count,
        image_bytes=png.tobytes(),
    )  # fmt: skip


class _Steps:
    """A stand-in for a navigation step dataset: instruction, frame, target box."""

    def __init__(self, n: int):
        self.n, self.epochs = n, []

    def __len__(self):
        return self.n

    def set_epoch(self, epoch):
        self.epochs.append(epoch)

    def __getitem__(self, i):
        return {
            C.OBS_RGB: np.zeros((8, 8, 3), np.uint8), C.OBS_INSTRUCTION: f"fly to {i}",
            C.BOX: np.array([0.5, 0.5, 0.2, 0.2]), C.BOX_VISIBLE: i % 2 == 0,
        }  # fmt: skip


def test_frame_dataset_draws_distinct_expressions_reproducibly_and_per_epoch():
    dataset = GroundingFrameDataset(
        [_frame(0, 6), _frame(1, 2), _frame(2, 0)], expressions_per_frame=3, seed=1
    )
    assert len(dataset) == 2  # the frame without expressions is dropped
    sample = dataset[0]
    assert sample[GROUNDING_KIND] == EXPRESSION_SAMPLE and len(sample[EXPRESSIONS]) == 3
    assert len(set(sample[EXPRESSIONS])) == 3
    for expression, box in zip(sample[EXPRESSIONS], sample[BOXES]):  # each box stays with its expression
        k = int(expression.rsplit(" ", 1)[1])
        np.testing.assert_allclose(box, [0.1 * (k + 1), 0.5, 0.1, 0.2], rtol=1e-6)
    assert dataset[0][EXPRESSIONS] == sample[EXPRESSIONS]
    assert len(dataset[1][EXPRESSIONS]) == 2  # fewer than asked: all of them
    assert (dataset[1][C.OBS_RGB] == 1).all()
    draws = set()
    for epoch in range(6):
        dataset.set_epoch(epoch)
        draws.add(tuple(dataset[0][EXPRESSIONS]))
    assert len(draws) > 1


def test_mixture_holds_the_asked_share_of_instruction_targets_and_cycles_them():
    steps = _Steps(5)
    mixture = GroundingMixture(GroundingFrameDataset([_frame(i, 3) for i in range(6)]), steps, 0.25)
    assert len(mixture) == 8  # 6 expression frames + 2 instruction samples = 25 %
    assert mixture[0][GROUNDING_KIND] == EXPRESSION_SAMPLE
    first = [mixture[i][C.OBS_INSTRUCTION] for i in (6, 7)]
    assert mixture[6][GROUNDING_KIND] == INSTRUCTION_SAMPLE and first == ["fly to 0", "fly to 1"]
    mixture.set_epoch(1)
    assert [mixture[i][C.OBS_INSTRUCTION] for i in (6, 7)] == ["fly to 2", "fly to 3"] and steps.epochs == [1]
    assert len(GroundingMixture(GroundingFrameDataset([_frame(0, 3)]), None, 0.5)) == 1
    with pytest.raises(ValueError, match="instruction_fraction"):
        GroundingMixture(GroundingFrameDataset([_frame(0, 3)]), steps, 1.0)


class _Processor:
    def grounding_prompt(self, text):
        return f"Where is {text}?"

    def navigation_prompt(self, text):
        return f"Go: {text}"

    def image(self, rgb):
        import torch

        return torch.from_numpy(rgb).permute(2, 0, 1)

    def __call__(self, prompts):
        import torch

        lengths = [len(p.split()) + 1 for p in prompts]
        ids = torch.zeros(len(prompts), max(lengths), dtype=torch.long)
        mask = torch.zeros_like(ids)
        for i, n in enumerate(lengths):
            ids[i, :n], mask[i, :n] = 1, 1
        return {C.INPUT_IDS: ids, C.ATTENTION_MASK: mask}


def test_collator_encodes_each_frame_once_and_points_every_sequence_at_its_frame():
    expressions = GroundingFrameDataset([_frame(3, 2), _frame(4, 3)], expressions_per_frame=3)
    samples = [expressions[0], expressions[1], GroundingMixture(expressions, _Steps(2), 0.5)[3]]
    batch = GroundingCollator(_Processor())(samples)
    assert batch[C.PIXEL_VALUES].shape == (3, 3, 8, 8)  # three frames
    assert batch[C.FRAME_INDEX].tolist() == [0, 0, 1, 1, 1, 2]
    assert batch[C.INPUT_IDS].shape[0] == 6 and C.LABELS not in batch
    assert batch[C.BOX_VISIBLE].tolist() == [True] * 5 + [False]  # instruction 1: target not visible
    assert batch[C.BOX][5].tolist() == [0, 0, 0, 0]  # a masked box is never a fake one
    np.testing.assert_allclose(batch[C.BOX][:2].numpy(), samples[0][BOXES])
    with pytest.raises(ValueError, match="empty"):
        GroundingCollator(_Processor())([])


def test_attributes_follow_each_expression_and_unknown_rows_are_minus_one():
    def lookup(scene_id: str, landmark_id: str) -> np.ndarray:  # "lm<k>" -> [k, k + 1, 0, scene seed]
        k = int(landmark_id.removeprefix("lm"))
        return np.array([k, k + 1, 0, int(scene_id.split("-")[1])], dtype=np.int64)

    expressions = GroundingFrameDataset([_frame(3, 2), _frame(4, 3)], 3, target_attributes=lookup)
    first = expressions[0]  # both expressions of a two-landmark frame, in order
    assert first[C.TARGET_ATTRIBUTES].tolist() == [[0, 1, 0, 0], [1, 2, 0, 0]]
    instruction = GroundingMixture(expressions, _Steps(2), 0.5)[3]  # a navigation step without attributes
    batch = GroundingCollator(_Processor())([first, instruction])
    assert batch[C.TARGET_ATTRIBUTES].tolist() == [[0, 1, 0, 0], [1, 2, 0, 0], [-1, -1, -1, -1]]
    plain = GroundingCollator(_Processor())([GroundingFrameDataset([_frame(3, 2)], 3)[0]])
    assert C.TARGET_ATTRIBUTES not in plain  # no lookup, no key: the loss then has no attribute term
