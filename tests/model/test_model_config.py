"""Model config: presets, YAML files, validation messages, dict round trip, token arithmetic."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import pytest

from openfly_agent.model.config import (
    LLAMA2_7B_ARCH,
    BoxGroundingConfig,
    CellGroundingConfig,
    DinoSiglipVisionConfig,
    DiscreteActionHeadConfig,
    HistoryEncodingConfig,
    Llama2LLMConfig,
    MemoryConfig,
    ModelConfig,
    NoGroundingConfig,
    TinyCnnVisionConfig,
    TinyLLMConfig,
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
        tiny_config(memory=MemoryConfig(encoding=HistoryEncodingConfig()))
    with pytest.raises(ValueError, match=r"box_token .* needs a head \(grounding.type=cells or box"):
        tiny_config(grounding=NoGroundingConfig(), action_head=DiscreteActionHeadConfig(box_token=True))
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


def test_each_llm_variant_has_only_its_own_fields():
    tiny, big = tiny_config().llm, openfly_7b_config().llm
    assert type(tiny) is TinyLLMConfig and tiny.type == "tiny"
    assert (tiny.hidden_size, tiny.num_layers, tiny.num_heads, tiny.intermediate_size) == (128, 2, 4, 344)
    assert type(big) is Llama2LLMConfig and big.type == "llama2-7b" and not hasattr(big, "num_layers")
    assert big.hidden_size == LLAMA2_7B_ARCH["hidden_size"] == 4096
    assert big.architecture == LLAMA2_7B_ARCH and tiny.architecture["num_hidden_layers"] == 2
    with pytest.raises(TypeError, match="hidden_size"):
        Llama2LLMConfig(hidden_size=4096)
    assert (big.default_vocab_size(None), tiny.default_vocab_size(600)) == (32064, 600 + 256)
    with pytest.raises(ValueError, match="sizes its vocabulary from the tokenizer"):
        tiny.default_vocab_size(None)


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
    old["llm"]["preset"] = old["llm"].pop("type")
    old["llm"].update({"hidden_size": 128, "num_layers": 2, "num_heads": 4, "intermediate_size": 344})
    assert OpenFlyAgentConfig(agent=old).model_config == openfly_7b_config()
    old["llm"]["hidden_size"] = 64
    with pytest.raises(ValueError, match="`hidden_size` are not valid for Llama2LLMConfig"):
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
    from openfly_agent.model.config_upgrade import RetiredOptionError, upgraded_model_dict
    from openfly_agent.model.pretrained_config import OpenFlyAgentConfig

    cfg = OpenFlyAgentConfig(agent=OLD_AGENT).model_config
    assert cfg.vision == TinyCnnVisionConfig()
    assert cfg.grounding == CellGroundingConfig()
    assert cfg.action_head == DiscreteActionHeadConfig(vocab_end=810)
    assert cfg.llm == TinyLLMConfig(vocab_size=810, pad_token_id=3)
    upgraded = upgraded_model_dict(OLD_AGENT)
    assert upgraded["vision"]["type"] == "tiny-cnn" and upgraded["grounding"]["type"] == "cells"
    assert upgraded_model_dict(upgraded) == upgraded  # today's layout passes unchanged
    box = {**OLD_AGENT, "grounding": {**OLD_AGENT["grounding"], "cells": False, "dim": 256, "num_heads": 8}}
    assert OpenFlyAgentConfig(agent=box).model_config.grounding == BoxGroundingConfig(dim=256, num_heads=8)
    on = {**OLD_AGENT, "grounding": {**OLD_AGENT["grounding"], "attribute_match": True}}
    with pytest.raises(RetiredOptionError, match="grounding.attribute_match was deleted.*7544758"):
        OpenFlyAgentConfig(agent=on)


# The sections of a config.json written at 505bc83, before issue 46, that the upgrade changes: the LLM a preset
# string (the tiny sizes filled in; null under llama2-7b), the memory encoding a top-level `mode`, the grounding
# head switched by a boolean, the action head's `n_bins` (256, the only value it took) (the tiny run's step-50
# checkpoint, vocabulary 864 with <pad> = 3).
BASE_TINY_AGENT = {
    "action_head": {
        "box_token": None, "box_token_jitter": 0.05, "n_bins": 256, "stop_loss_weight": 1.0, "type": "discrete",
        "vocab_end": 864,
    },
    "llm": {
        "attn_implementation": "sdpa", "bos_token_id": 1, "eos_token_id": 2, "hidden_size": 128,
        "intermediate_size": 344, "length_groups": 3, "max_length": 2048, "num_heads": 4, "num_layers": 2,
        "pad_token_id": 3, "preset": "tiny", "tokenizer_path": None, "vocab_size": 864,
    },
    "grounding": {**config_to_dict(CellGroundingConfig()), "enabled": True, "num_queries": 1},
    "memory": {"capacity": 2, "grid": 8},
    "mode": "openfly",
    "projector": {"hidden_ratio": 4},
}  # fmt: skip


def test_a_config_json_of_before_the_llm_and_memory_variants_loads_the_same_model():
    from openfly_agent.model.config_upgrade import upgraded_model_dict
    from openfly_agent.model.pretrained_config import OpenFlyAgentConfig

    cfg = OpenFlyAgentConfig(agent=BASE_TINY_AGENT).model_config
    assert cfg == tiny_config(
        llm=TinyLLMConfig(vocab_size=864, pad_token_id=3), action_head=DiscreteActionHeadConfig(vocab_end=864)
    )
    assert upgraded_model_dict(BASE_TINY_AGENT)["llm"]["type"] == "tiny"
    no_head = {**BASE_TINY_AGENT, "grounding": {**BASE_TINY_AGENT["grounding"], "enabled": False, "dim": 64}}
    no_head["action_head"] = {"box_token": None}  # None: on when a head is enabled, so off
    cfg = OpenFlyAgentConfig(agent=no_head).model_config
    assert cfg.grounding == NoGroundingConfig() and cfg.grounding.type == "none" and not cfg.uses_box_token
    released = config_to_dict(openvla_compat_7b_config())  # today's layout, then as 505bc83 wrote it
    released["mode"] = "openvla_compat"
    del released["memory"]["encoding"]
    released["llm"]["preset"] = released["llm"].pop("type")
    released["llm"].update(dict.fromkeys(("hidden_size", "num_layers", "num_heads", "intermediate_size")))
    released["grounding"]["enabled"] = True
    assert OpenFlyAgentConfig(agent=released).model_config == openvla_compat_7b_config()
    assert upgraded_model_dict(upgraded_model_dict(released)) == upgraded_model_dict(released)


def test_the_settings_fixed_by_issue_46_load_at_their_value_and_refuse_any_other():
    """`projector.hidden_ratio` (4) and `grounding.num_queries` (1) were settings that no config changed; a
    config.json holding them at those values loads as today's model, any other value names the commit to use."""
    from openfly_agent.model.config_upgrade import RetiredOptionError, upgraded_model_dict
    from openfly_agent.model.pretrained_config import OpenFlyAgentConfig

    upgraded = upgraded_model_dict(BASE_TINY_AGENT)
    assert "projector" not in upgraded and "num_queries" not in upgraded["grounding"]
    wide = {**BASE_TINY_AGENT, "projector": {"hidden_ratio": 8}}
    with pytest.raises(RetiredOptionError, match=r"projector.hidden_ratio is fixed at 4 .*commit 32e260f"):
        OpenFlyAgentConfig(agent=wide)
    queries = {**BASE_TINY_AGENT, "grounding": {**BASE_TINY_AGENT["grounding"], "num_queries": 2}}
    with pytest.raises(RetiredOptionError, match=r"grounding.num_queries is fixed at 1 .*commit 32e260f"):
        OpenFlyAgentConfig(agent=queries)


def test_the_deleted_stop_weight_loads_at_one_and_refuses_any_other():
    """`action_head.stop_loss_weight` was deleted after its measured arm (no gain): a config.json at 1.0 (every
    config written before) loads as today's model, a weighted one names the commit that trains it."""
    from openfly_agent.model.config_upgrade import RetiredOptionError, upgraded_model_dict
    from openfly_agent.model.pretrained_config import OpenFlyAgentConfig

    assert "stop_loss_weight" not in upgraded_model_dict(BASE_TINY_AGENT)["action_head"]
    assert "stop_loss_weight" not in upgraded_model_dict(OLD_AGENT)["action_head"]
    weighted = {**BASE_TINY_AGENT, "action_head": {**BASE_TINY_AGENT["action_head"], "stop_loss_weight": 4.0}}
    with pytest.raises(
        RetiredOptionError, match=r"action_head.stop_loss_weight was deleted .*commit 9046d6d"
    ):
        OpenFlyAgentConfig(agent=weighted)


@pytest.mark.parametrize(
    "section, name, kept, trained, commit",
    [
        # the auxiliary leg-goal target (docs/experiments/2026-11-28-long-route-ablation.md): the arm set 1.0
        ("action_head", "leg_goal_weight", 0.0, 1.0, "1cb4fad"),
        # the agent's last actions in its prompt (docs/experiments/2026-11-29-main-job-action-history.md, val
        # -16.7 points at seed 9): the arms named 4 and 1
        ("prompt", "action_history", 0, 4, "5925c14"),
        # the action trained on the head's own boxes (docs/experiments/2026-11-30-main-job-own-boxes.md, val -5.6
        # points at seed 9): the arm set 0.5
        ("action_head", "box_token_predicted_fraction", 0.0, 0.5, "d6f1b4e"),
        # the colour match (docs/experiments/2026-11-30-main-job-colour-match.md, its ask colour-blind at the gate
        # in four grounding stages): the arms set 16
        ("grounding", "colour_match", 0, 16, "7dc778f"),
    ],
)
def test_a_field_deleted_after_its_arm_loads_at_its_default_and_refuses_any_other(
    section, name, kept, trained, commit
):
    """A field deleted after its measured arm (no gain): a config.json written while it existed (its default
    unless an arm set it) loads as today's model; the arm's own value names the commit that has the field."""
    from openfly_agent.model.config_upgrade import RetiredOptionError, upgraded_model_dict
    from openfly_agent.model.pretrained_config import OpenFlyAgentConfig

    def agent_with(value):
        return {**BASE_TINY_AGENT, section: {**BASE_TINY_AGENT.get(section, {}), name: value}}

    assert name not in upgraded_model_dict(agent_with(kept)).get(section, {})
    with pytest.raises(RetiredOptionError, match=rf"{section}.{name} was deleted .*commit {commit}"):
        OpenFlyAgentConfig(agent=agent_with(trained))
