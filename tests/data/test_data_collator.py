"""NavigationCollator: the batch contract of docs/INTERFACES.md, through a real OpenFlyProcessor around a small
word-level tokenizer built here (the processor's own text rules are tested in tests/model/test_model_processor.py)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import torch
from data_factories import make_episode, make_frames

from openfly_agent import constants as C
from openfly_agent.data.collator import NavigationCollator
from openfly_agent.data.dataset import NavigationStepDataset
from openfly_agent.data.frames import FrameStore
from openfly_agent.data.writer import OpenFlyDatasetWriter
from openfly_agent.model.language.action_tokenizer import CODEBOOK, ActionTokenizer
from openfly_agent.model.processor import OpenFlyProcessor

WORDS = ["what", "action", "should", "the", "robot", "take", "to", "fly", "red", "tower", "?", "1", "2", "3"]
BATCH_KEYS = {
    C.INPUT_IDS, C.ATTENTION_MASK, C.LABELS, C.PIXEL_VALUES, C.MEMORY_PIXEL_VALUES, C.MEMORY_FRAME_MASK,
    C.MEMORY_BOXES, C.MEMORY_BOX_VISIBLE, C.BOX, C.BOX_VISIBLE, C.ACTION,
}  # fmt: skip


@pytest.fixture(scope="module")
def tokenizer():
    from tokenizers import Tokenizer, models, pre_tokenizers, processors
    from transformers import PreTrainedTokenizerFast

    vocab = {w: i for i, w in enumerate(["<pad>", "<unk>", "<s>", "</s>", *WORDS])}
    for a in range(16):  # the "last ids", used for actions
        vocab[f"<act{a}>"] = len(vocab)
    core = Tokenizer(models.WordLevel(vocab, unk_token="<unk>"))
    core.pre_tokenizer = pre_tokenizers.WhitespaceSplit()
    core.post_processor = processors.TemplateProcessing(single="<s> $A", special_tokens=[("<s>", 2)])
    return PreTrainedTokenizerFast(
        tokenizer_object=core, bos_token="<s>", eos_token="</s>", pad_token="<pad>", unk_token="<unk>"
    )


TEMPLATE = "what action should the robot take to {instruction} ?"
NORM_STATS = {"q01": [0.0] * 8, "q99": CODEBOOK.max(axis=0).tolist()}


def make_processor(tokenizer, head: str = "discrete", **kwargs) -> OpenFlyProcessor:
    """8 x 8 px area resize, the lowercased template above; action ids right after the tokenizer's ids."""
    actions = ActionTokenizer(head, vocab_end=len(tokenizer) + 256, eos_token_id=tokenizer.eos_token_id)
    stats = NORM_STATS if head == "openvla_bins" else None
    return OpenFlyProcessor(
        tokenizer, image_size=8, resize="area", prompt_template=TEMPLATE, lowercase=True,
        action_head=actions.to_dict(), action_stats=stats, **kwargs,
    )  # fmt: skip


def resize_8(rgb: np.ndarray) -> torch.Tensor:
    return (
        torch.from_numpy(cv2.resize(rgb, (8, 8), interpolation=cv2.INTER_AREA)).permute(2, 0, 1).contiguous()
    )


def prompt(instruction: str) -> str:
    return f"what action should the robot take to {instruction.lower()} ?"


@pytest.fixture()
def dataset(tmp_path):
    episodes = [
        make_episode(
            "embedded-1/astar_data/low_short/a", [9, 2, 9, 1, 9, 0], seed=1, instruction="fly to red tower"
        ),
        make_episode(
            "embedded-1/astar_data/low_short/b", [9, 3, 0], with_boxes=False, seed=2, instruction="fly"
        ),
    ]
    writer = OpenFlyDatasetWriter(tmp_path)
    for i, episode in enumerate(episodes):
        writer.write_episode(episode, make_frames(len(episode), seed=i))
    return NavigationStepDataset(episodes, FrameStore(tmp_path), "uniform", capacity=2, set_size=3)


def _collator(tokenizer, **kwargs):
    return NavigationCollator(make_processor(tokenizer), capacity=2, set_size=3, **kwargs)


def test_batch_contract(tokenizer, dataset):
    samples = [dataset[i] for i in (0, 3, 7, 8)]  # a t=0, a t=3, b t=1, b t=2
    batch = _collator(tokenizer)(samples)
    assert set(batch) == BATCH_KEYS
    prompt_a = tokenizer(prompt("fly to red tower"))["input_ids"]
    prompt_b = tokenizer(prompt("fly"))["input_ids"]
    assert prompt_a[0] == tokenizer.bos_token_id and len(prompt_a) == 13 and len(prompt_b) == 10
    b, length = 4, 14
    assert batch[C.INPUT_IDS].shape == (b, length) and batch[C.INPUT_IDS].dtype == torch.long
    assert batch[C.ATTENTION_MASK].tolist() == [[1] * 14, [1] * 14, [1] * 11 + [0] * 3, [1] * 11 + [0] * 3]
    act = [len(tokenizer) + a for a in (9, 1, 3, 0)]  # the discrete head: vocab_end - 256 + action
    assert batch[C.INPUT_IDS][0].tolist() == prompt_a + [act[0]]
    assert batch[C.INPUT_IDS][2].tolist() == prompt_b + [act[2]] + [tokenizer.pad_token_id] * 3
    labels = batch[C.LABELS]
    assert labels.dtype == torch.long
    assert (
        labels[0].tolist() == [-100] * 13 + [act[0]]
        and labels[3].tolist() == [-100] * 10 + [act[3]] + [-100] * 3
    )
    assert (labels != -100).sum().item() == 4
    assert batch[C.ACTION].tolist() == [9, 1, 3, 0] and batch[C.ACTION].dtype == torch.long
    assert batch[C.PIXEL_VALUES].shape == (b, 3, 8, 8) and batch[C.PIXEL_VALUES].dtype == torch.uint8
    assert torch.equal(batch[C.PIXEL_VALUES][1], resize_8(samples[1][C.OBS_RGB]))
    assert batch[C.MEMORY_PIXEL_VALUES].shape == (b, 2, 3, 3, 8, 8)
    assert batch[C.MEMORY_PIXEL_VALUES].dtype == torch.uint8
    # memory: a t=0 none; a t=3 frames 0 and 2 (uniform); b t=1 frame 0; b t=2 frames 0 and 1
    expected_mask = torch.zeros(b, 2, 3, dtype=torch.bool)
    expected_mask[1, :, 0] = expected_mask[2, 0, 0] = expected_mask[3, :, 0] = True
    assert torch.equal(batch[C.MEMORY_FRAME_MASK], expected_mask)
    assert torch.equal(batch[C.MEMORY_PIXEL_VALUES][1, 1, 0], resize_8(samples[1][C.MEMORY][1][0][0]))
    assert not batch[C.MEMORY_PIXEL_VALUES][~expected_mask].any()
    assert batch[C.MEMORY_BOXES].dtype == torch.float32 and batch[C.MEMORY_BOX_VISIBLE].dtype == torch.bool
    episode_a = dataset.episodes[0]
    assert batch[C.MEMORY_BOX_VISIBLE][1, :, 0].tolist() == [True, True]  # frames 0 and 2 are visible
    assert torch.allclose(
        batch[C.MEMORY_BOXES][1, 1, 0], torch.tensor(episode_a.boxes[2], dtype=torch.float32)
    )
    assert batch[C.BOX].shape == (b, 4) and batch[C.BOX].dtype == torch.float32
    assert batch[C.BOX_VISIBLE].tolist() == [True, False, False, False]
    assert torch.allclose(batch[C.BOX][0], torch.tensor(episode_a.boxes[0], dtype=torch.float32))
    assert not batch[C.BOX][1:].any()  # invisible: zeros, masked


def test_eight_action_tokens_eos_and_truncation(tokenizer, dataset):
    collator = NavigationCollator(make_processor(tokenizer, "openvla_bins", max_length=12), 2, 3)
    batch = collator([dataset[0], dataset[6]])
    assert batch[C.INPUT_IDS].shape == (2, 12)
    eos = tokenizer.eos_token_id
    # sample 0 (13 prompt tokens) is cut to 3 so that 8 action tokens + EOS fit
    assert batch[C.INPUT_IDS][0, :3].tolist() == tokenizer(prompt("fly to red tower"))["input_ids"][:3]
    assert batch[C.LABELS][0].tolist()[:3] == [-100] * 3 and batch[C.LABELS][0, -1].item() == eos
    assert (batch[C.LABELS] != -100).sum(dim=1).tolist() == [9, 9]  # 8 bins + one EOS, never two
    with pytest.raises(ValueError, match="no room"):
        NavigationCollator(make_processor(tokenizer, "openvla_bins", max_length=8), 2, 3)([dataset[0]])


class _BadImages:
    """A processor whose image() returns the frame unchanged (a numpy array, not a tensor)."""

    def __init__(self, processor):
        self.processor = processor

    def __call__(self, *args, **kwargs):
        return self.processor(*args, **kwargs)

    def navigation_prompt(self, instruction):
        return self.processor.navigation_prompt(instruction)

    def image(self, rgb):
        return rgb


def test_metadata_and_bad_transform(tokenizer, dataset):
    batch = _collator(tokenizer, with_metadata=True)([dataset[4], dataset[8]])
    assert batch[C.EPISODE_ID] == [dataset.episodes[0].episode_id, dataset.episodes[1].episode_id]
    assert batch[C.STEP_INDEX].tolist() == [4, 2]
    bad = NavigationCollator(_BadImages(make_processor(tokenizer)), 2, 3)
    with pytest.raises(ValueError, match=r"\(3, h, w\) uint8 tensor"):
        bad([dataset[3]])  # a sample with memory frames


def test_dataloader_with_workers_matches_in_process(tokenizer, dataset):
    collator = _collator(tokenizer)
    expected = [
        collator([dataset[i] for i in range(j, min(j + 4, len(dataset)))]) for j in range(0, len(dataset), 4)
    ]
    loader = torch.utils.data.DataLoader(dataset, batch_size=4, num_workers=2, collate_fn=collator)
    got = list(loader)
    assert len(got) == len(expected)
    for a, b in zip(got, expected):
        assert all(torch.equal(a[k], b[k]) for k in BATCH_KEYS)
