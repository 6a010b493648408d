"""Model config: presets, YAML files, validation messages, dict round trip, token arithmetic."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import pytest

from openfly_agent.model.config import (
    LLAMA2_7B_ARCH,
    TINY_CNN_VISION,
    TINY_LLM,
    TINY_VISION,
    LLMConfig,
    MemoryConfig,
    ModelConfig,
    VisionConfig,
    make_model_config,
    openfly_7b_config,
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
        VisionConfig(preset="dinosiglip-224px", image_size=112)
    with pytest.raises(ValueError, match="action_head.type=openvla_bins"):
        tiny_config(mode="openvla_compat")
    with pytest.raises(ValueError, match="unknown model preset"):
        make_model_config("huge")


def test_tiny_only_fields_are_filled_for_tiny_and_rejected_for_7b():
    tiny = tiny_config()
    assert {name: getattr(tiny.vision, name) for name in TINY_CNN_VISION} == TINY_CNN_VISION
    assert all(getattr(tiny.vision, name) is None for name in TINY_VISION)  # the ViT sizes: not the CNN's
    vit = VisionConfig(preset="tiny", image_size=112, patch_size=14)
    assert {name: getattr(vit, name) for name in TINY_VISION} == TINY_VISION
    with pytest.raises(ValueError, match=r"vision.width=96 is read by the tiny preset only"):
        VisionConfig(width=96)  # tiny-cnn
    assert {name: getattr(tiny.llm, name) for name in TINY_LLM} == TINY_LLM
    big = openfly_7b_config()
    assert all(getattr(big.vision, name) is None for name in TINY_VISION)
    assert all(getattr(big.llm, name) is None for name in TINY_LLM)
    assert big.llm.resolved_hidden_size == LLAMA2_7B_ARCH["hidden_size"] == 4096
    with pytest.raises(ValueError, match=r"llm.hidden_size=4096 is read by the tiny preset only.*remove"):
        LLMConfig(preset="llama2-7b", hidden_size=4096)
    with pytest.raises(ValueError, match=r"vision.depth=24 is read by the tiny preset only"):
        VisionConfig(preset="dinosiglip-224px", image_size=224, depth=24)
    vit = VisionConfig(preset="tiny", image_size=112, patch_size=14, width=64, num_heads=2)
    assert vit.fused_width == TINY_VISION["fused_width"]  # unset: the default


def test_config_json_of_older_7b_checkpoints_still_loads():
    """Before the tiny-only sizes became optional, a 7B config.json held the tiny sizes too; those exact values
    are dropped on load, anything else still fails."""
    from openfly_agent.model.pretrained_config import OpenFlyAgentConfig

    old = config_to_dict(openfly_7b_config())
    old["vision"].update(TINY_VISION)
    old["llm"].update(TINY_LLM)
    assert OpenFlyAgentConfig(agent=old).model_config == openfly_7b_config()
    old["llm"]["hidden_size"] = 64
    with pytest.raises(ValueError, match="llm.hidden_size=64 is read by the tiny preset only"):
        OpenFlyAgentConfig(agent=old)
