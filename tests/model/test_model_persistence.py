"""save_pretrained -> from_pretrained equality, sharding, freeze stages, LoRA attach / save / merge."""

from __future__ import annotations

import json
import subprocess
import sys
import warnings

import numpy as np
import pytest
import torch

from openfly_agent.model.agent import OpenFlyAgent
from openfly_agent.model.config import BinsActionHeadConfig, LoraSettings
from openfly_agent.model.freeze import FREEZE_STAGES
from openfly_agent.model.language.action_tokenizer import CODEBOOK
from openfly_agent.model.language.lora import (
    attach_lora,
    has_lora,
    load_lora_adapter,
    merge_lora,
    save_lora_adapter,
)
from openfly_agent.utils.processes import run_group

NORM_STATS = {"demo": {"action": {"q01": [0.0] * 8, "q99": CODEBOOK.max(axis=0).tolist()}}}


def _logits(agent, batch) -> torch.Tensor:
    """Full-vocabulary logits at every position of the training layout (eval mode, no grad)."""
    from openfly_agent.model.layout import SequenceLayout

    network = agent.network
    with torch.no_grad():
        text = network.embed_text(batch["input_ids"])
        no_labels = torch.full_like(batch["input_ids"], -100)
        layout = SequenceLayout.for_training(text, batch["attention_mask"], no_labels, *network.encode(batch))
        return network.lm_logits(network(layout))


def test_save_load_gives_identical_logits(make_agent, make_batch, tmp_path):
    agent = make_agent(action_head=BinsActionHeadConfig(), norm_stats=NORM_STATS)
    batch = make_batch(agent)
    agent.save_pretrained(tmp_path)
    files = {p.name for p in tmp_path.iterdir()}
    assert {"config.json", "model.safetensors", "action_tokenizer.json", "dataset_statistics.json"} <= files
    assert "tokenizer.json" in files
    config = json.loads((tmp_path / "config.json").read_text())
    assert config["model_type"] == "openfly_agent" and config["norm_stats"] == NORM_STATS
    assert config["agent"]["action_head"]["type"] == "openvla_bins"

    loaded = OpenFlyAgent.from_pretrained(tmp_path).eval()
    assert loaded.tokenizer is not None and len(loaded.tokenizer) == len(agent.tokenizer)
    assert loaded.model_cfg == agent.model_cfg
    own, other = agent.state_dict(), loaded.state_dict()
    assert own.keys() == other.keys()
    assert all(torch.equal(own[k], other[k]) for k in own)
    assert torch.equal(_logits(agent, batch), _logits(loaded, batch))
    assert agent(batch)[1] == loaded(batch)[1]
    assert [loaded.action_tokenizer.action_to_token_ids(a) for a in range(10)] == [
        agent.action_tokenizer.action_to_token_ids(a) for a in range(10)
    ]


def test_sharded_save_loads(make_agent, make_batch, tmp_path):
    agent = make_agent()
    agent.save_pretrained(tmp_path, max_shard_size="200KB")
    assert (tmp_path / "model.safetensors.index.json").is_file()
    assert len(list(tmp_path.glob("model-*.safetensors"))) > 1
    loaded = OpenFlyAgent.from_pretrained(tmp_path).eval()
    batch = make_batch(agent)
    assert torch.equal(_logits(agent, batch), _logits(loaded, batch))


def test_loaded_agent_acts_like_the_saved_one(make_agent, tmp_path):
    agent = make_agent()
    agent.save_pretrained(tmp_path)
    loaded = OpenFlyAgent.from_pretrained(tmp_path).eval()
    own_session, loaded_session = agent.new_session(), loaded.new_session()
    rng = np.random.default_rng(0)
    for _ in range(3):
        obs = [
            {
                "episode_id": "a",
                "instruction": "Go to the tower.",
                "rgb": rng.integers(0, 256, (80, 60, 3), np.uint8),
            }
        ]
        ours, theirs = own_session.predict_step(obs)[0], loaded_session.predict_step(obs)[0]
        assert ours.action == theirs.action
        # bit-identical weights; memory-mapped tensors may take other SIMD paths (~1e-8 differences)
        torch.testing.assert_close(ours.action_logits, theirs.action_logits, rtol=0, atol=1e-6)


@pytest.mark.parametrize("stage", FREEZE_STAGES)
def test_freeze_stages(make_agent, stage):
    agent = make_agent()
    if stage == "lora":
        attach_lora(agent, LoraSettings(rank=4, alpha=8))
    counts = agent.freeze(stage)
    trains = {name: p.requires_grad for name, p in agent.network.named_parameters()}  # as saved

    def part(prefix):
        return {trains[n] for n in trains if n.startswith(prefix)}

    expected = {
        "full": ({True}, {True}, {True}, {True}),
        "frozen_vision": ({False}, {True}, {True}, {True}),
        "heads_only": ({False}, {False}, {True, False}, {True}),
        "lora": ({False}, {True}, {True, False}, {True}),
    }[stage]
    assert (
        part("vision_backbone."),
        part("projector."),
        part("language_model."),
        part("grounding_head."),
    ) == expected
    if stage == "heads_only":
        assert [n for n in trains if n.startswith("language_model.") and trains[n]] == [
            "language_model.lm_head.weight"
        ]
    if stage == "lora":
        assert all("lora_" in n for n in trains if n.startswith("language_model.") and trains[n])
    assert sum(counts.values()) == sum(p.numel() for p in agent.parameters() if p.requires_grad)


def test_freeze_errors(make_agent):
    agent = make_agent()
    with pytest.raises(ValueError, match="unknown freeze stage"):
        agent.freeze("everything")
    with pytest.raises(ValueError, match="needs LoRA adapters"):
        agent.freeze("lora")


def test_attaching_and_loading_lora_raise_no_future_warning(make_agent, tmp_path):
    """peft's FutureWarning about transformers' deprecated `is_gradient_checkpointing`, which it reads when it
    wraps a model, is not shown on every LoRA run (issue 48)."""
    agent = make_agent()
    agent.save_pretrained(tmp_path / "base")
    with warnings.catch_warnings():
        warnings.simplefilter("error", FutureWarning)
        attach_lora(agent, LoraSettings(rank=4, alpha=8))
        save_lora_adapter(agent, tmp_path / "run")
        load_lora_adapter(OpenFlyAgent.from_pretrained(tmp_path / "base").eval(), tmp_path / "run")


def test_lora_merge_equals_unmerged_and_adapter_round_trip(make_agent, make_batch, tmp_path):
    agent = make_agent()
    batch = make_batch(agent)
    base_logits = _logits(agent, batch)
    agent.save_pretrained(tmp_path / "base")
    attach_lora(agent, LoraSettings(rank=4, alpha=8))
    with torch.no_grad():  # peft starts B at zero (a no-op); make the adapter do something
        for name, param in agent.named_parameters():
            if "lora_B" in name:
                param.normal_(std=0.05)
        agent.network.projector.fc3.bias.add_(0.1)
    unmerged = _logits(agent, batch)
    assert not torch.allclose(unmerged, base_logits, atol=1e-4)
    with pytest.raises(ValueError, match="LoRA is attached"):
        agent.save_pretrained(tmp_path / "nope")

    save_lora_adapter(agent, tmp_path / "run")
    reloaded = load_lora_adapter(OpenFlyAgent.from_pretrained(tmp_path / "base").eval(), tmp_path / "run")
    torch.testing.assert_close(_logits(reloaded, batch), unmerged, rtol=1e-5, atol=1e-5)

    merge_lora(agent)
    assert not has_lora(agent)
    assert not any("lora_" in k for k in agent.state_dict())
    torch.testing.assert_close(_logits(agent, batch), unmerged, rtol=1e-4, atol=1e-4)
    agent.save_pretrained(tmp_path / "merged")
    merged = OpenFlyAgent.from_pretrained(tmp_path / "merged").eval()
    assert torch.equal(_logits(merged, batch), _logits(agent, batch))


def test_auto_model_registration(make_agent, tmp_path):
    from transformers import AutoModel

    from openfly_agent.model import OpenFlyAgent as Lazy
    from openfly_agent.model import register_auto_classes

    assert Lazy is OpenFlyAgent
    make_agent().save_pretrained(tmp_path)
    register_auto_classes()
    loaded = AutoModel.from_pretrained(tmp_path)
    assert isinstance(loaded, OpenFlyAgent)


def test_save_with_push_uploads_the_complete_folder(make_agent, tmp_path, monkeypatch):
    agent = make_agent()
    calls = []

    def fake_push(repo_id, **kwargs):  # the network is off: record what would be pushed
        calls.append((repo_id, kwargs, sorted(p.name for p in tmp_path.iterdir())))

    monkeypatch.setattr(agent, "push_to_hub", fake_push)
    agent.save_pretrained(tmp_path, push_to_hub=True, repo_id="me/agent", max_shard_size="1GB")
    (repo_id, kwargs, files) = calls[0]
    assert repo_id == "me/agent" and kwargs == {"max_shard_size": "1GB"}
    assert {"action_tokenizer.json", "tokenizer.json", "model.safetensors"} <= set(files)


def _training_run(agent, root):
    """`agent` saved as a training run lays it out: <run>/checkpoints/step-000002 and the `last` pointer."""
    step = root / "run" / "checkpoints" / "step-000002"
    agent.save_pretrained(step)
    (root / "run" / "checkpoints" / "last").write_text("step-000002\n")
    return root / "run", step


def test_from_pretrained_takes_a_run_its_pointer_or_a_step_folder(make_agent, tmp_path):
    agent = make_agent()
    run, step = _training_run(agent, tmp_path)
    expected = agent.state_dict()
    for path in (run, run / "checkpoints", run / "checkpoints" / "last", step):
        loaded = OpenFlyAgent.from_pretrained(path)
        assert loaded.processor is not None and loaded.processor.to_dict() == agent.processor.to_dict(), path
        for key, value in loaded.state_dict().items():
            assert torch.equal(value, expected[key]), (path, key)
    with pytest.raises(FileNotFoundError, match="pass a checkpoint folder"):
        OpenFlyAgent.from_pretrained(tmp_path)  # exists, but neither a checkpoint nor a run


def test_auto_model_loads_a_training_checkpoint_or_says_what_to_pass(make_agent, tmp_path):
    from transformers import AutoModel

    agent = make_agent()
    _, step = _training_run(agent, tmp_path)
    loaded = AutoModel.from_pretrained(step, trust_remote_code=True)
    assert type(loaded).__name__ == "OpenFlyAgent" and loaded.processor is not None
    assert all(torch.equal(v, agent.state_dict()[k]) for k, v in loaded.state_dict().items())
    # a fresh process (nothing registered): without trust_remote_code, transformers names the argument to pass
    code = f"from transformers import AutoModel\nAutoModel.from_pretrained({str(step)!r})"
    done = run_group([sys.executable, "-c", code], timeout=300, stdin=subprocess.DEVNULL)
    assert done.returncode != 0 and "pass the argument `trust_remote_code=True`" in done.stderr, done.stderr[
        -2000:
    ]


def test_a_lora_only_checkpoint_says_what_loads_it(make_agent, tmp_path):
    from openfly_agent.training.export import write_lora_folder

    agent = make_agent()
    attach_lora(agent, LoraSettings(rank=2, alpha=4))
    write_lora_folder(agent, agent.state_dict(), tmp_path)
    with pytest.raises(ValueError, match="LoRA checkpoint .*load_lora_agent"):
        OpenFlyAgent.from_pretrained(tmp_path)


def test_a_lora_run_folder_names_its_merged_model(make_agent, tmp_path):
    """eval and the release load `<run>/merged`; from_pretrained(<run>) says to load exactly that folder."""
    from openfly_agent.training.export import write_lora_folder

    agent = make_agent()
    attach_lora(agent, LoraSettings(rank=2, alpha=4))
    run = tmp_path / "run"
    write_lora_folder(agent, agent.state_dict(), run / "checkpoints" / "step-000002")
    (run / "checkpoints" / "last").write_text("step-000002\n")
    make_agent().save_pretrained(run / "merged")
    for path in (run, run / "checkpoints" / "last"):
        with pytest.raises(ValueError) as raised:
            OpenFlyAgent.from_pretrained(path)
        message = str(raised.value)
        assert f"{path} is a LoRA training run" in message and f"load {run / 'merged'}" in message, message
        assert "\n" not in message


def test_decoding_overrides_go_through_the_config(make_agent, tmp_path):
    """eval's decode_rule / unnorm_key reach the config, `config.action_tokenizer`, the action tokenizer and the
    processor together (none can go stale)."""
    from openfly_agent.rollout.checkpoints import load_agent

    stats = {"a": NORM_STATS["demo"], "b": {"action": {"q01": [-1.0] * 8, "q99": [20.0] * 8}}}
    head = BinsActionHeadConfig(unnorm_key="a", decode_rule="exact")
    make_agent(action_head=head, norm_stats=stats).save_pretrained(tmp_path)
    agent = load_agent(str(tmp_path), "cpu", dtype="float32", decode_rule="nearest", unnorm_key="b")
    assert (
        agent.model_cfg.action_head.decode_rule == "nearest" and agent.model_cfg.action_head.unnorm_key == "b"
    )
    assert agent.config.agent["action_head"]["decode_rule"] == "nearest"
    for settings in (
        agent.config.action_tokenizer,
        agent.action_tokenizer.to_dict(),
        agent.processor.action_head,
    ):
        assert settings["decode_rule"] == "nearest"
    for tokenizer in (agent.action_tokenizer, agent.processor.action_tokenizer):
        np.testing.assert_array_equal(tokenizer.action_stats["q99"], [20.0] * 8)
    agent.save_pretrained(tmp_path / "again")
    saved = json.loads((tmp_path / "again" / "processor_config.json").read_text())
    assert saved["action_head"]["decode_rule"] == "nearest" and saved["action_stats"]["q99"] == [20.0] * 8
