"""Each registered config variant builds its own module (model/config_choice.py): every variant of the vision, LLM,
grounding and memory-encoding sections has its builder, `build` gives that variant's module, and a variant without
one is named."""

from __future__ import annotations

from dataclasses import dataclass

import pytest
import torch
from draccus import ChoiceRegistry

import openfly_agent.model.network  # noqa: F401 (imports the modules of every section's variants)
from openfly_agent.model.config import (
    BoxGroundingConfig,
    CellGroundingConfig,
    GroundingConfig,
    Llama2LLMConfig,
    LLMConfig,
    MemoryEncodingConfig,
    NoGroundingConfig,
    TinyCnnVisionConfig,
    TinyLLMConfig,
    TinyVitVisionConfig,
    VisionConfig,
)
from openfly_agent.model.config_choice import BuiltChoice
from openfly_agent.model.grounding.head import BoxRegressionHead, CellGroundingHead
from openfly_agent.model.vision.backbone import TinyVitBackbone
from openfly_agent.model.vision.conv import ConvVisionBackbone


@pytest.mark.parametrize("section", [VisionConfig, LLMConfig, GroundingConfig, MemoryEncodingConfig])
def test_every_registered_variant_has_its_builder(section):
    for name in section.get_known_choices():
        assert callable(section.get_choice_class(name).builder()), name


def test_each_variant_builds_its_module():
    assert type(TinyCnnVisionConfig(cnn_channels=[8, 8, 8, 8]).build()) is ConvVisionBackbone
    vit = TinyVitVisionConfig(
        image_size=56, patch_size=14, width=32, fused_width=48, depth=2, num_heads=2
    ).build()
    assert (
        type(vit) is TinyVitBackbone
        and vit.featurizer.embed_dim == 32
        and vit.fused_featurizer.embed_dim == 48
    )
    cells = CellGroundingConfig(dim=16, num_heads=2).build(24, 4)
    assert type(cells) is CellGroundingHead and cells.grid_side == 4
    assert type(BoxGroundingConfig(dim=16, num_heads=2).build(24, 4)) is BoxRegressionHead
    assert NoGroundingConfig().build(24, 4) is None
    tiny = TinyLLMConfig(hidden_size=32, num_layers=1, num_heads=2, intermediate_size=64).build(300).config
    assert (tiny.hidden_size, tiny.num_hidden_layers, tiny.intermediate_size, tiny.vocab_size) == (
        32,
        1,
        64,
        300,
    )
    with torch.device("meta"):
        big = Llama2LLMConfig().build(32064).config
    assert (big.hidden_size, big.num_hidden_layers, big.intermediate_size, big.vocab_size) == (
        4096,
        32,
        11008,
        32064,
    )


@dataclass
class _Section(BuiltChoice, ChoiceRegistry):
    pass


@_Section.register_subclass("a")
@dataclass
class _A(_Section):
    pass


@_Section.register_subclass("b")
@dataclass
class _B(_A):  # a variant that subclasses another
    pass


def test_a_variant_builds_with_its_own_builder_only():
    with pytest.raises(TypeError, match="no builder is registered for _A"):
        _A().build()

    @_A.register_builder
    def built(cfg, width):
        return ("built", type(cfg).__name__, width)

    assert _A().build(3) == ("built", "_A", 3)
    with pytest.raises(TypeError, match="no builder is registered for _B"):
        _B().build(3)  # not inherited from _A
    with pytest.raises(TypeError, match="_A is built by .*built already"):
        _A.register_builder(lambda cfg, width: None)
