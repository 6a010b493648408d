"""The memory encoding chosen once from the config (`memory.encoding.type`, model/factory.py::make_memory_encoding,
model/memory/)."""

from __future__ import annotations

import pytest
import torch

from openfly_agent.model.config import make_model_config
from openfly_agent.model.factory import make_memory_encoding
from openfly_agent.model.memory.history_memory import HistoryEpisodeMemory, HistoryMemory, history_indices
from openfly_agent.model.memory.keyframe_memory import KeyframeEpisodeMemory, KeyframeMemory, MemoryBank
from openfly_agent.model.memory.keyframes import KeyframeSelector


@pytest.mark.parametrize(
    ("preset", "name", "encoding", "episode_memory"),
    [
        ("tiny", "keyframes", KeyframeMemory, KeyframeEpisodeMemory),
        ("openvla-compat-7b", "openvla_history", HistoryMemory, HistoryEpisodeMemory),
    ],
)
def test_each_encoding_variant_builds_its_encoding(preset, name, encoding, episode_memory):
    cfg = make_model_config(preset)  # sections only: cheap
    assert cfg.memory.encoding.type == name
    selector = KeyframeSelector.from_config(cfg.keyframes, cfg.memory.capacity)
    chosen = make_memory_encoding(cfg, selector)
    assert type(chosen) is encoding
    memory = chosen.new_episode()
    assert type(memory) is episode_memory and memory.sets() == [] and len(memory) == 0


def test_the_agent_builds_the_encoding_of_its_config(make_agent):
    assert isinstance(make_agent().network.memory, KeyframeMemory)


def test_a_keyframe_memory_lists_its_sets_oldest_first():
    cfg = make_model_config("tiny")
    encoding = KeyframeMemory(cfg, KeyframeSelector.from_config(cfg.keyframes, 2))
    memory = encoding.new_episode()
    for frames in [(0, 1), (2, 3), (4, 5)]:
        memory.bank.push(frames, torch.zeros(1, 4))
    assert memory.sets() == [(2, 3), (4, 5)] and len(memory) == 2  # capacity 2: the oldest was evicted


def test_history_indices():
    assert history_indices(0, 2) == [0, 0]
    assert history_indices(1, 2) == [0, 0]  # eval: [f0, f0, f1]
    assert history_indices(2, 2) == [0, 1]
    assert history_indices(7, 2) == [5, 6]


def test_memory_bank_fifo_eviction_order():
    bank = MemoryBank(capacity=2)
    assert bank.push("a", torch.zeros(1)) == []
    assert bank.push("b", torch.ones(1)) == []
    assert bank.push("b", torch.ones(1)) == []  # already stored: no change
    assert bank.push("c", torch.full((1,), 2.0)) == ["a"]
    assert bank.keys() == ["b", "c"]
    assert [t.item() for t in bank.tokens()] == [1.0, 2.0]
    assert bank.push("d", torch.full((1,), 3.0)) == ["b"]
    assert bank.keys() == ["c", "d"] and "b" not in bank
    bank.clear()
    assert len(bank) == 0
    zero = MemoryBank(capacity=0)
    assert zero.push("a", torch.zeros(1)) == [] and len(zero) == 0
