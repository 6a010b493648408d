"""OpenVLA key layout: a synthetic checkpoint written here (tiny dims, real names) loads by name."""

from __future__ import annotations

import json

import pytest
import torch
from safetensors.torch import save_file
from timm.models.vision_transformer import VisionTransformer
from transformers import LlamaConfig, LlamaForCausalLM

from openfly_agent.model.persistence.openvla_loader import (
    NEW_MODULE_PREFIXES,
    agent_from_openvla_checkpoint,
    load_openvla_weights,
    read_openvla_norm_stats,
    to_openvla_state_dict,
)

NORM_STATS = {"vlnv1": {"action": {"q01": [0.0] * 8, "q99": [1, 9, 15, 15, 2, 2, 5, 5]}}}


def _openvla_state_dict(agent, seed: int = 0) -> dict[str, torch.Tensor]:
    """What OpenVLA's HF converter writes, at the agent's small dims: full timm ViTs, LayerScale renamed."""
    torch.manual_seed(seed)
    v = agent.model_cfg.vision
    common = {"img_size": v.image_size, "patch_size": v.patch_size, "depth": v.depth, "num_classes": 0}
    dino = VisionTransformer(
        embed_dim=v.width, num_heads=v.num_heads, init_values=0.3, reg_tokens=4, no_embed_class=True, **common
    )
    siglip = VisionTransformer(
        embed_dim=v.fused_width,
        num_heads=v.num_heads,
        mlp_ratio=3.7362,
        class_token=False,
        global_pool="map",
        **common,
    )
    llm_cfg = agent.network.language_model.config
    llm = LlamaForCausalLM(
        LlamaConfig(
            vocab_size=llm_cfg.vocab_size,
            hidden_size=llm_cfg.hidden_size,
            intermediate_size=llm_cfg.intermediate_size,
            num_hidden_layers=llm_cfg.num_hidden_layers,
            num_attention_heads=llm_cfg.num_attention_heads,
            rms_norm_eps=1e-5,
            tie_word_embeddings=False,
        )
    )
    dv, d = v.width + v.fused_width, llm_cfg.hidden_size
    state = {}
    for prefix, vit in (("vision_backbone.featurizer.", dino), ("vision_backbone.fused_featurizer.", siglip)):
        for key, value in vit.state_dict().items():
            state[prefix + key.replace(".gamma", ".scale_factor")] = value.clone()
    for name, shape in (("fc1", (4 * dv, dv)), ("fc2", (d, 4 * dv)), ("fc3", (d, d))):
        state[f"projector.{name}.weight"] = torch.randn(shape) * 0.02
        state[f"projector.{name}.bias"] = torch.randn(shape[0]) * 0.02
    for key, value in llm.state_dict().items():
        state["language_model." + key] = value.clone()
    state["_dino"], state["_siglip"] = dino, siglip  # kept for the forward comparison, removed before saving
    return state


def _write_sharded(state: dict, folder) -> None:
    folder.mkdir()
    keys = sorted(k for k in state if not k.startswith("_"))
    halves = {"model-00001-of-00002.safetensors": keys[::2], "model-00002-of-00002.safetensors": keys[1::2]}
    weight_map = {}
    for file, names in halves.items():
        save_file({k: state[k].contiguous() for k in names}, str(folder / file))
        weight_map.update(dict.fromkeys(names, file))
    (folder / "model.safetensors.index.json").write_text(
        json.dumps({"metadata": {}, "weight_map": weight_map})
    )
    (folder / "config.json").write_text(json.dumps({"model_type": "openvla", "norm_stats": NORM_STATS}))


def test_synthetic_openvla_checkpoint_loads_by_name(make_agent, tmp_path):
    agent = make_agent()
    state = _openvla_state_dict(agent)
    _write_sharded(state, tmp_path / "ckpt")
    report = load_openvla_weights(agent, tmp_path / "ckpt")

    new = sorted(k for k in agent.network.state_dict() if k.startswith(NEW_MODULE_PREFIXES))
    assert report.missing_new == new
    assert report.missing_new  # the only thing the checkpoint lacks
    last = agent.model_cfg.vision.depth - 1
    assert sorted(report.unused) == sorted(
        k
        for k in state
        if k.startswith(
            (
                f"vision_backbone.featurizer.blocks.{last}.",
                "vision_backbone.featurizer.norm.",
                f"vision_backbone.fused_featurizer.blocks.{last}.",
                "vision_backbone.fused_featurizer.norm.",
                "vision_backbone.fused_featurizer.attn_pool.",
            )
        )
    )
    assert len(report.loaded) + len(report.unused) == len([k for k in state if not k.startswith("_")])
    block = agent.network.vision_backbone.featurizer.blocks[0]
    assert torch.equal(block.ls1.gamma, state["vision_backbone.featurizer.blocks.0.ls1.scale_factor"])
    assert torch.equal(agent.network.projector.fc2.weight, state["projector.fc2.weight"])
    assert torch.equal(agent.network.language_model.lm_head.weight, state["language_model.lm_head.weight"])

    # the pruned backbone computes OpenVLA's features: second-to-last block, no final norm
    pixels = torch.randint(0, 256, (2, 3, 56, 56), dtype=torch.uint8)
    ours = agent.network.vision_backbone(pixels)
    x = pixels.float() / 255
    dino_in = (x - torch.tensor([0.485, 0.456, 0.406]).view(1, 3, 1, 1)) / torch.tensor(
        [0.229, 0.224, 0.225]
    ).view(1, 3, 1, 1)
    reference = torch.cat(
        [
            state["_dino"].eval().get_intermediate_layers(dino_in, n={last - 1})[0],
            state["_siglip"].eval().get_intermediate_layers((x - 0.5) / 0.5, n={last - 1})[0],
        ],
        dim=-1,
    )
    torch.testing.assert_close(ours, reference, rtol=1e-5, atol=1e-5)


def test_loader_fails_loudly(make_agent):
    agent = make_agent()
    state = {k: v for k, v in _openvla_state_dict(agent).items() if not k.startswith("_")}
    with pytest.raises(
        ValueError, match=r"config: 1 unexpected key: vision_backbone.featurizer.head.weight;"
    ):
        load_openvla_weights(agent, {**state, "vision_backbone.featurizer.head.weight": torch.zeros(3)})
    without = dict(state)
    del without["projector.fc1.bias"]
    with pytest.raises(ValueError, match=r"config: 1 missing key: projector.fc1.bias;"):
        load_openvla_weights(agent, without)
    resized = dict(state)
    resized["language_model.model.embed_tokens.weight"] = torch.zeros(10, 64)
    with pytest.raises(
        ValueError, match=r"1 tensor of another shape \(checkpoint vs config\): .*embed_tokens"
    ):
        load_openvla_weights(agent, resized)


def test_export_round_trip(make_agent):
    source, target = make_agent(seed=1), make_agent(seed=2)
    exported = to_openvla_state_dict(source)
    assert any(k.endswith("ls1.scale_factor") for k in exported)
    assert not any(k.endswith(".gamma") or k.startswith(NEW_MODULE_PREFIXES) for k in exported)
    load_openvla_weights(target, exported)
    for key, value in source.network.state_dict().items():
        if not key.startswith(NEW_MODULE_PREFIXES):
            assert torch.equal(target.network.state_dict()[key], value), key


def test_agent_from_checkpoint_on_meta_then_materialised(make_agent, small_config, tiny_tokenizer, tmp_path):
    reference = make_agent()
    state = _openvla_state_dict(reference)
    _write_sharded(state, tmp_path / "ckpt")
    load_openvla_weights(reference, tmp_path / "ckpt")
    assert read_openvla_norm_stats(tmp_path / "ckpt") == NORM_STATS
    agent, report = agent_from_openvla_checkpoint(tmp_path / "ckpt", small_config(), tokenizer=tiny_tokenizer)
    assert agent.config.norm_stats == NORM_STATS and report.missing_new
    assert all(not p.is_meta for p in agent.parameters())
    assert torch.isfinite(agent.network.grounding_head.box_queries).all()
    # the new modules (not in an OpenVLA checkpoint) are freshly initialised: give them the reference's weights,
    # since the box token feeds the grounding head's box to the action
    for name in ("grounding_head", "box_token_embed"):
        getattr(agent.network, name).load_state_dict(getattr(reference.network, name).state_dict())
    frame = torch.randint(0, 256, (56, 56, 3), dtype=torch.uint8).numpy()
    obs = [{"episode_id": "a", "instruction": "Fly to the red tower.", "rgb": frame}]
    torch.testing.assert_close(
        agent.new_session().predict_step(obs)[0].action_logits,
        reference.new_session().predict_step(obs)[0].action_logits,
        rtol=1e-5,
        atol=1e-5,
    )
