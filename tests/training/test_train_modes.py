"""LoRA runs (adapter checkpoints, rank-0 CPU merge), gradient checkpointing, init checkpoints and checks."""

from __future__ import annotations

import json
import logging
import shutil
from pathlib import Path

import pytest
import torch
from conftest import built_agent, make_config, split_batch, train_args, train_in_process, train_main

from openfly_agent import constants as C
from openfly_agent.training.preflight import PreflightError
from openfly_agent.training.resume_settings import CONFIG_CHANGES_NAME

LORA_RUN = {"steps": 2, "freeze_stage": "lora", "lora__rank": 4, "lora__alpha": 8, "optim__lr": 1e-2,
            "validation__final_eval": "false"}  # fmt: skip


@pytest.fixture(scope="module")
def lora_run(generated_dataset, tmp_path_factory):
    """A finished 2-step LoRA run (a checkpoint at step 2, merged/ at the end): (output_dir, cfg, TrainResult)."""
    out = tmp_path_factory.mktemp("lora_run")
    cfg = make_config(generated_dataset, out, **LORA_RUN)
    return out, cfg, train_in_process(cfg)


def test_lora_run_saves_the_adapter_and_merges_on_rank0(lora_run):
    from openfly_agent.model.agent import OpenFlyAgent
    from openfly_agent.model.language.lora import TRAINABLES_NAME

    tmp_path, cfg, result = lora_run
    adapter = result.checkpoint / C.ADAPTER_DIR_NAME
    assert (adapter / "adapter_config.json").is_file() and (adapter / TRAINABLES_NAME).is_file()
    assert not (result.checkpoint / C.WEIGHTS_NAME).exists()  # base weights are not copied into checkpoints
    assert (result.checkpoint / C.CONFIG_NAME).is_file() and (
        result.checkpoint / C.ACTION_TOKENIZER_NAME
    ).is_file()
    merged = OpenFlyAgent.from_pretrained(str(tmp_path / "merged")).eval()
    assert not any("lora_" in k for k in merged.state_dict())
    lora_agent = result.agent.eval()
    batch = split_batch(cfg, lora_agent, cfg.data.test_split, range(4))
    with torch.no_grad():
        expected, _ = lora_agent(batch)
        found, _ = merged(batch)
    torch.testing.assert_close(found, expected, rtol=1e-4, atol=1e-5)
    b = (
        lora_agent.network.language_model.base_model.model.model.layers[0]
        .self_attn.q_proj.lora_B["default"]
        .weight
    )
    assert b.abs().max() > 0  # the adapter trained, so the merge really changed the weights


def _run_files(folder: Path) -> dict[str, tuple[int, int]]:
    """Every file of a run folder (links as themselves) but its logs and setting changes: path -> (size, mtime_ns)."""
    files = [p for p in sorted(folder.rglob("*")) if p.is_file() or p.is_symlink()]
    return {
        str(p.relative_to(folder)): (p.lstat().st_size, p.lstat().st_mtime_ns)
        for p in files
        if p.relative_to(folder).parts[0] not in ("logs", CONFIG_CHANGES_NAME)
    }


def test_a_resume_with_nothing_left_to_train_writes_nothing(lora_run, generated_dataset, tmp_path, caplog):
    """The run's last checkpoint and merged model stay as they were (eval.py and the release identify weights by
    their files' sizes and modification times), the log says why, and the command succeeds."""
    done, _, _ = lora_run
    run = tmp_path / "run"
    shutil.copytree(done, run, symlinks=True)  # copy2: the modification times come along
    before = _run_files(run)
    assert "merged/model.safetensors" in before and "checkpoints/step-000002/trainer_state.json" in before
    args = train_args(generated_dataset, run, resume="true", **LORA_RUN)
    with caplog.at_level(logging.INFO, logger="openfly_agent.training.run_setup"):
        assert train_main(args) == 0
    # the copy's resume records that the run moved (output_dir), as any resume records what it changed
    [moved] = (run / CONFIG_CHANGES_NAME).read_text().splitlines()
    assert list(json.loads(moved)["changes"]) == ["output_dir"]
    assert _run_files(run) == before
    step = run / "checkpoints" / "step-000002"
    assert (
        f"nothing left to train: {step} is at step 2 of the 2 configured; no checkpoint is written and its "
        "weights are left as they are"
    ) in caplog.text


def test_gradient_checkpointing_gives_the_same_loss_and_gradients(generated_dataset, tmp_path):
    from openfly_agent.training.modes import enable_gradient_checkpointing

    cfg = make_config(generated_dataset, tmp_path, freeze_stage="full", validation__final_eval="false")
    agent = built_agent(cfg).train()
    batch = split_batch(cfg, agent, cfg.data.test_split, range(2))
    torch.manual_seed(0)  # the same box-token jitter in both passes
    loss, _ = agent(batch)
    loss.backward()
    plain = {n: p.grad.clone() for n, p in agent.named_parameters() if p.grad is not None}
    agent.zero_grad()
    switched = enable_gradient_checkpointing(agent)
    assert any("layers" in n for n in switched) and any("featurizer" in n for n in switched)
    torch.manual_seed(0)
    again, _ = agent(batch)
    again.backward()
    torch.testing.assert_close(again, loss)
    for name, grad in plain.items():
        torch.testing.assert_close(agent.get_parameter(name).grad, grad, rtol=1e-4, atol=1e-6, msg=name)


def test_decoder_checkpointing_uses_the_older_transformers_name_when_the_new_one_is_missing():
    from openfly_agent.training.modes import switch_on_decoder_checkpointing

    class OlderTransformersModel(torch.nn.Module):  # transformers 5.17: no activation_checkpointing_enable
        def gradient_checkpointing_enable(self, gradient_checkpointing_kwargs=None):
            self.called_with = gradient_checkpointing_kwargs

    class NewerTransformersModel(OlderTransformersModel):
        def activation_checkpointing_enable(self, activation_checkpointing_kwargs=None):
            self.new_called_with = activation_checkpointing_kwargs

    older, newer = OlderTransformersModel(), NewerTransformersModel()
    switch_on_decoder_checkpointing(older)
    switch_on_decoder_checkpointing(newer)
    assert older.called_with == {"use_reentrant": False}
    assert newer.new_called_with == {"use_reentrant": False} and not hasattr(newer, "called_with")


def test_init_checkpoint_of_another_architecture_fails_before_training(
    reference_run, generated_dataset, tmp_path
):
    _, result = reference_run
    cfg = make_config(
        generated_dataset, tmp_path, init__checkpoint=str(result.checkpoint), model__llm__hidden_size=64
    )
    with pytest.raises(PreflightError, match=r"model\.llm\.hidden_size: checkpoint 128, config 64"):
        train_in_process(cfg)
    assert not (tmp_path / "checkpoints").exists()  # failed before any training step


def test_init_from_our_checkpoint_starts_from_its_weights(reference_run, generated_dataset, tmp_path):
    _, result = reference_run
    cfg = make_config(generated_dataset, tmp_path, init__checkpoint=str(result.checkpoint))
    trained = result.agent.state_dict()
    for key, value in built_agent(cfg).state_dict().items():
        torch.testing.assert_close(value, trained[key], rtol=0, atol=0, msg=key)


def test_compiled_decoder_layers_are_off_by_default_and_give_the_same_loss(generated_dataset, tmp_path):
    """`compile_layers` compiles each decoder layer in place (here with the `eager` backend: the wiring, not
    inductor's kernels, which need a GPU session to be worth timing); the default compiles nothing."""
    from openfly_agent.training.modes import compile_decoder_layers

    cfg = make_config(generated_dataset, tmp_path, validation__final_eval="false")
    assert cfg.compile_layers is False
    agent = built_agent(cfg).train()
    layers = agent.network.causal_lm.model.layers
    assert all(layer._compiled_call_impl is None for layer in layers)
    batch = split_batch(cfg, agent, cfg.data.test_split, range(2))
    torch.manual_seed(0)  # the same box-token jitter in both passes
    loss, _ = agent(batch)
    keys = set(agent.state_dict())
    assert compile_decoder_layers(agent, backend="eager") == len(layers)
    assert all(layer._compiled_call_impl is not None for layer in layers)
    torch.manual_seed(0)
    again, _ = agent(batch)
    torch.testing.assert_close(again, loss)
    assert set(agent.state_dict()) == keys  # checkpoints keep their names
