"""Model config: presets, YAML files, validation messages, dict round trip, token arithmetic."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import pytest

from openfly_agent.model.config import (
    LLAMA2_7B_ARCH,
    TINY_LLM,
    BoxGroundingConfig,
    CellGroundingConfig,
    DinoSiglipVisionConfig,
    LLMConfig,
    MemoryConfig,
    ModelConfig,
    TinyCnnVisionConfig,
    TinyVitVisionConfig,
    VisionConfig,
    make_model_config,
    openfly_7b_config,
    openvla_compat_7b_config,
    tiny_config,
)
from openfly_agent.utils.config import config_from_dict, config_to_dict, load_yaml_config

REPO_ROOT = Path(__file__).resolve().parents[2]


@pytest.mark.parametrize("name", ["tiny", "openfly-7b", "openvla-compat-7b"])
def test_yaml_presets_equal_the_python_presets(name):
    loaded = load_yaml_config(ModelConfig, REPO_ROOT / "configs" / "model" / f"{name}.yaml")
    assert loaded == make_model_config(name)


def test_token_counts():
    cfg = openfly_7b_config()
    assert cfg.vision.num_patches == 256 and cfg.vision.feature_dim == 2176
    assert cfg.memory_tokens_per_set == 1
    assert cfg.visual_tokens_per_step() == 258  # 256 + K * (16 / 16)^2
    g4 = dataclasses.replace(cfg, memory=MemoryConfig(capacity=2, grid=4))
    assert g4.visual_tokens_per_step() == 256 + 2 * 16
    assert tiny_config().visual_tokens_per_step() == 64 + 2


def test_dict_round_trip():
    cfg = openfly_7b_config()
    assert config_from_dict(ModelConfig, config_to_dict(cfg)) == cfg
    with pytest.raises(
        ValueError, match="^ModelConfig: memory: The fields `gird` are not valid for MemoryConfig$"
    ):
        config_from_dict(ModelConfig, {**config_to_dict(cfg), "memory": {"capacity": 2, "gird": 16}})
    with pytest.raises(ValueError, match="^ModelConfig: memory.capacity: expected an int, got 'x'$"):
        config_from_dict(ModelConfig, {"memory": {"capacity": "x"}})
    with pytest.raises(ValueError, match="memory.capacity=-1 must be >= 0"):
        config_from_dict(ModelConfig, {"memory": {"capacity": -1}})


def test_validation_messages_say_what_to_change():
    with pytest.raises(ValueError, match="memory.grid=3 must divide the patch grid side 16"):
        openfly_7b_config(memory=MemoryConfig(grid=3))
    with pytest.raises(ValueError, match="multiple of vision.patch_size"):
        VisionConfig(image_size=100, patch_size=14)
    with pytest.raises(ValueError, match="dinosiglip-224px needs image_size=224"):
        DinoSiglipVisionConfig(image_size=112)
    with pytest.raises(ValueError, match="action_head.type=openvla_bins"):
        tiny_config(mode="openvla_compat")
    with pytest.raises(ValueError, match="unknown model preset"):
        make_model_config("huge")


def test_each_vision_variant_has_only_its_own_fields():
    tiny = tiny_config()
    assert type(tiny.vision) is TinyCnnVisionConfig and tiny.vision.type == "tiny-cnn"
    assert tiny.vision.cnn_channels == [32, 64, 96, 128] and not hasattr(tiny.vision, "width")
    vit = TinyVitVisionConfig(image_size=112, patch_size=14, width=64, num_heads=2)
    assert (vit.type, vit.fused_width, vit.depth) == ("tiny", 128, 3)  # unset: the variant's defaults
    assert vit.featurizer_widths == (64, 128) and not hasattr(vit, "cnn_channels")
    with pytest.raises(TypeError, match="width"):
        TinyCnnVisionConfig(width=96)
    big = openfly_7b_config()
    assert big.vision == DinoSiglipVisionConfig() and big.vision.feature_dim == 2176
    with pytest.raises(TypeError, match="depth"):
        DinoSiglipVisionConfig(depth=24)
    assert {name: getattr(tiny.llm, name) for name in TINY_LLM} == TINY_LLM
    assert all(getattr(big.llm, name) is None for name in TINY_LLM)
    assert big.llm.resolved_hidden_size == LLAMA2_7B_ARCH["hidden_size"] == 4096
    with pytest.raises(ValueError, match=r"llm.hidden_size=4096 is read by the tiny preset only.*remove"):
        LLMConfig(preset="llama2-7b", hidden_size=4096)


def test_the_variants_serialise_under_type_and_parse_from_yaml_and_flags(tmp_path):
    from openfly_agent.utils.config import load_yaml_config

    cfg = openvla_compat_7b_config()
    data = config_to_dict(cfg)
    assert data["vision"]["type"] == "dinosiglip-224px" and data["grounding"] == {
        "type": "box",
        **data["grounding"],
    }
    assert data["action_head"]["type"] == "openvla_bins" and "box_token" not in data["action_head"]
    assert config_from_dict(ModelConfig, data) == cfg
    path = tmp_path / "model.yaml"
    path.write_text("vision: {type: tiny, image_size: 112, patch_size: 14}\ngrounding: {type: box}\n")
    parsed = load_yaml_config(ModelConfig, path, ["--grounding.dim=64", "--vision.depth=4"])
    assert parsed.vision == TinyVitVisionConfig(image_size=112, patch_size=14, depth=4)
    assert parsed.grounding == BoxGroundingConfig(dim=64)
    flags = ["--vision.type=tiny-cnn", "--vision.image_size=128", "--vision.patch_size=16"]
    assert (
        load_yaml_config(ModelConfig, path, flags).vision == TinyCnnVisionConfig()
    )  # the ResNet's own defaults


def test_config_json_of_older_7b_checkpoints_still_loads():
    """Before the tiny-only sizes became optional, a 7B config.json held the tiny sizes too; those exact values
    are dropped on load, anything else still fails."""
    from openfly_agent.model.pretrained_config import OpenFlyAgentConfig

    old = config_to_dict(openfly_7b_config())
    old["llm"].update(TINY_LLM)
    assert OpenFlyAgentConfig(agent=old).model_config == openfly_7b_config()
    old["llm"]["hidden_size"] = 64
    with pytest.raises(ValueError, match="llm.hidden_size=64 is read by the tiny preset only"):
        OpenFlyAgentConfig(agent=old)


# The model sections of a config.json written before issue 40 (`agent` of the tiny run's step-50 checkpoint, the
# sections the upgrade changes): flat vision and grounding sections with every variant's fields and the deleted
# switches at their off values.
OLD_AGENT = {
    "action_head": {
        "box_token": None, "box_token_jitter": 0.05, "decode_rule": "exact", "n_bins": 256,
        "stop_loss_weight": 1.0, "type": "discrete", "unnorm_key": None, "vocab_end": 810,
    },
    "grounding": {
        "attribute_classes": [12, 6, 3, 8], "attribute_match": False, "attribute_weight": 0.0,
        "cell_fusion_layers": 0, "cell_weight": 1.0, "cells": True, "centre_window": 1,
        "dense_attribute_weight": 0.0, "dim": 128, "enabled": True, "l1_weight": 1.0, "loss_weight": 1.0,
        "num_heads": 4, "num_layers": 3, "num_queries": 1, "subcells": 1, "visibility_weight": 0.5,
        "visual_skip": False,
    },
    "llm": {"vocab_size": 810, "pad_token_id": 3},
    "vision": {
        "cnn_channels": [32, 64, 96, 128], "cnn_colour_stats": False, "cnn_fine_fusion": False,
        "cnn_init": "normal", "cnn_instruction_film": False, "cnn_stem": "resnet", "cnn_stem_width": 16,
        "depth": None, "fused_width": None, "image_size": 128, "num_heads": None, "patch_size": 16,
        "preset": "tiny-cnn", "resize": "bicubic", "width": None,
    },
}  # fmt: skip


def test_an_old_flat_config_json_loads_as_its_variants():
    from openfly_agent.model.config import DiscreteActionHeadConfig, LLMConfig
    from openfly_agent.model.config_upgrade import RetiredOptionError, upgraded_model_dict
    from openfly_agent.model.pretrained_config import OpenFlyAgentConfig

    cfg = OpenFlyAgentConfig(agent=OLD_AGENT).model_config
    assert cfg.vision == TinyCnnVisionConfig()
    assert cfg.grounding == CellGroundingConfig()
    assert cfg.action_head == DiscreteActionHeadConfig(vocab_end=810)
    assert cfg.llm == LLMConfig(vocab_size=810, pad_token_id=3)
    upgraded = upgraded_model_dict(OLD_AGENT)
    assert upgraded["vision"]["type"] == "tiny-cnn" and upgraded["grounding"]["type"] == "cells"
    assert upgraded_model_dict(upgraded) == upgraded  # today's layout passes unchanged
    box = {**OLD_AGENT, "grounding": {**OLD_AGENT["grounding"], "cells": False, "dim": 256, "num_heads": 8}}
    assert OpenFlyAgentConfig(agent=box).model_config.grounding == BoxGroundingConfig(dim=256, num_heads=8)
    on = {**OLD_AGENT, "grounding": {**OLD_AGENT["grounding"], "attribute_match": True}}
    with pytest.raises(RetiredOptionError, match="grounding.attribute_match was deleted.*7544758"):
        OpenFlyAgentConfig(agent=on)
