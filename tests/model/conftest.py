"""Fixtures for the model tests: a tiny tokenizer, tiny agents and training batches in the collator format."""

from __future__ import annotations

import dataclasses

import pytest
import torch

from openfly_agent.model.config import CellGroundingConfig, TinyVitVisionConfig

INSTRUCTIONS = [
    "Fly forward to the red skyscraper with a rooftop billboard, then turn left at the tower.",
    "Ascend above the white house and stop near the blue dome.",
    "Turn right after the park and go straight until the spire.",
    "Descend next to the grey tower and land on the roof of the small house.",
]


@pytest.fixture(scope="session")
def tiny_tokenizer(tmp_path_factory):
    from openfly_agent.model.language.tokenizer import train_bpe_tokenizer

    return train_bpe_tokenizer(INSTRUCTIONS * 4, vocab_size=320, out_dir=tmp_path_factory.mktemp("tok"))


def small_config(**overrides):
    """The tiny preset shrunk further (2 blocks of width 32/48 at 56 px, 4x4 patches) for fast tests."""
    from openfly_agent.model.config import MemoryConfig, TinyLLMConfig, tiny_config

    cfg = tiny_config(
        vision=TinyVitVisionConfig(
            image_size=56, patch_size=14, width=32, fused_width=48, depth=3, num_heads=2
        ),
        llm=TinyLLMConfig(hidden_size=64, num_layers=2, num_heads=2, intermediate_size=128),
        grounding=CellGroundingConfig(dim=32, num_heads=2),
        memory=MemoryConfig(capacity=2, grid=2),
    )
    return dataclasses.replace(cfg, **overrides)


@pytest.fixture
def make_agent(tiny_tokenizer):
    """Factory: a freshly initialised small agent in eval mode (seeded)."""
    from openfly_agent.model.agent import OpenFlyAgent

    def _make(seed: int = 0, norm_stats=None, **overrides):
        torch.manual_seed(seed)
        agent = OpenFlyAgent.from_model_config(
            small_config(**overrides), tokenizer=tiny_tokenizer, norm_stats=norm_stats
        )
        return agent.eval()

    return _make


@pytest.fixture
def make_batch():
    """Factory: a training batch with the keys and dtypes of docs/INTERFACES.md for `agent`."""

    def _make(agent, batch_size: int = 3, capacity: int | None = None, set_size: int = 5, seed: int = 0):
        gen = torch.Generator().manual_seed(seed)
        processor = agent.processor
        size = agent.model_cfg.vision.image_size
        k = agent.model_cfg.memory.capacity if capacity is None else capacity
        actions = torch.randint(0, 10, (batch_size,), generator=gen)
        text = processor(
            [processor.navigation_prompt(INSTRUCTIONS[i % len(INSTRUCTIONS)]) for i in range(batch_size)],
            actions=actions.tolist(),
        )  # the training text of docs/INTERFACES.md: [BOS] prompt action, right padded
        input_ids, attention_mask, labels = text["input_ids"], text["attention_mask"], text["labels"]
        frame_mask = torch.rand(batch_size, k, set_size, generator=gen) > 0.3
        frame_mask[:, :, 0] = True
        return {
            "input_ids": input_ids,
            "attention_mask": attention_mask,
            "labels": labels,
            "pixel_values": torch.randint(
                0, 256, (batch_size, 3, size, size), generator=gen, dtype=torch.uint8
            ),
            "memory_pixel_values": torch.randint(
                0, 256, (batch_size, k, set_size, 3, size, size), generator=gen, dtype=torch.uint8
            ),
            "memory_frame_mask": frame_mask,
            "memory_boxes": torch.rand(batch_size, k, set_size, 4, generator=gen) * 0.5 + 0.25,
            "memory_box_visible": torch.rand(batch_size, k, set_size, generator=gen) > 0.2,
            "box": torch.rand(batch_size, 4, generator=gen) * 0.5 + 0.25,
            "box_visible": torch.tensor([True, False] * batch_size)[:batch_size],
            "action": actions,
        }

    return _make


@pytest.fixture(name="small_config")
def _small_config_fixture():
    """The `small_config` factory."""
    return small_config
