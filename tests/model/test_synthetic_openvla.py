"""bench/synthetic_openvla.py: the full layout has the released openvla-7b's parameters; a written folder loads."""

from __future__ import annotations

import dataclasses
import importlib
import json

import pytest

from openfly_agent.model.persistence.openvla_loader import agent_from_openvla_checkpoint, load_openvla_weights


def test_the_full_layout_counts_the_released_openvla_7b_parameters():
    writer = importlib.import_module("bench.synthetic_openvla")
    from openfly_agent.model.language.tokenizer import train_bpe_tokenizer

    shapes = writer.openvla_shapes(writer.model_config("full"), train_bpe_tokenizer(writer.CORPUS, 1024))
    assert sum(shape.numel() for shape in shapes.values()) == 7_541_237_184  # built on the meta device
    assert (
        "vision_backbone.featurizer.blocks.23.ls1.scale_factor" in shapes
    )  # the pruned last block, as released
    assert shapes["language_model.model.embed_tokens.weight"] == (32064, 4096)
    groups = writer.shard_keys(shapes, 3)
    assert len(groups) == 3 and sum(map(len, groups)) == len(shapes)


def test_a_reduced_folder_is_laid_out_as_released_and_loads_by_name(tmp_path, tiny_tokenizer):
    writer = importlib.import_module("bench.synthetic_openvla")
    from openfly_agent.model.agent import OpenFlyAgent

    summary = writer.write_synthetic_openvla(tmp_path / "openvla", "reduced")
    folder = tmp_path / "openvla"
    index = json.loads((folder / "model.safetensors.index.json").read_text())
    assert sorted(set(index["weight_map"].values())) == [
        f"model-0000{i}-of-00003.safetensors" for i in (1, 2, 3)
    ]
    assert json.loads((folder / "config.json").read_text())["model_type"] == "openvla"
    assert summary["tensors"] == len(index["weight_map"]) and (folder / "tokenizer.json").is_file()
    agent = OpenFlyAgent.from_model_config(writer.model_config("reduced"), tokenizer=tiny_tokenizer)
    report = load_openvla_weights(agent, folder)
    assert len(report.loaded) + len(report.unused) == summary["tensors"] and report.unused


def test_a_7b_config_on_a_reduced_width_folder_is_one_readable_line(tmp_path):
    """The 7B model config on the reduced folder (configs/model/reduced-width.yaml forgotten): one line that names
    the sizes that differ and the file, read from the headers before the 7B weights are allocated."""
    writer = importlib.import_module("bench.synthetic_openvla")
    from openfly_agent.model.language.tokenizer import load_tokenizer

    folder = tmp_path / "openvla"
    writer.write_synthetic_openvla(folder, "reduced")
    with pytest.raises(ValueError) as info:
        agent_from_openvla_checkpoint(folder, writer.model_config("full"), tokenizer=load_tokenizer(folder))
    message = str(info.value)
    assert "\n" not in message and len(message) < 1200, message
    # tiny Llama 128 wide vs Llama-2-7B 4096; tiny ViTs 96 / 128 wide vs ViT-L 1024 / So400m 1152, 14 px patches both
    assert message.startswith(
        f"OpenVLA checkpoint {folder} does not match the model config: checkpoint llm hidden size 128, config "
        "4096; checkpoint vision width 96, config 1024; checkpoint fused vision width 128, config 1152; "
    ), message
    assert "checkpoint vision patch size" not in message
    assert message.endswith(
        "; did you forget --model=configs/model/reduced-width.yaml? (or use the model config "
        "the checkpoint was made for)"
    )


def test_a_wider_llm_than_the_checkpoint_names_the_size_first(tmp_path, tiny_tokenizer):
    """Loading into a built agent whose LLM is 256 wide, from the reduced folder's 128-wide one."""
    writer = importlib.import_module("bench.synthetic_openvla")
    from openfly_agent.model.agent import OpenFlyAgent

    folder = tmp_path / "openvla"
    writer.write_synthetic_openvla(folder, "reduced")
    cfg = writer.model_config("reduced")
    cfg.llm = dataclasses.replace(cfg.llm, hidden_size=256)
    agent = OpenFlyAgent.from_model_config(cfg, tokenizer=tiny_tokenizer)
    with pytest.raises(ValueError) as info:
        load_openvla_weights(agent, folder)
    message = str(info.value)
    assert "\n" not in message and len(message) < 1200, message
    sizes = f"OpenVLA checkpoint {folder} does not match the model config: checkpoint llm hidden size 128, config 256; "
    # 2 layers x 9 (q, k, v, o, gate, up, down, 2 norms) + embed_tokens, lm_head, final norm + projector fc2, fc3
    # (weight and bias) = 25
    assert message.startswith(sizes + "25 tensors of another shape (checkpoint vs config), e.g. "), message
    assert "unexpected" not in message and "missing" not in message
