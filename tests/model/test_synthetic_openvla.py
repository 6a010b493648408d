"""bench/synthetic_openvla.py: the full layout has the released openvla-7b's parameters; a written folder loads."""

from __future__ import annotations

import importlib
import json

from openfly_agent.model.persistence.openvla_loader import load_openvla_weights


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
