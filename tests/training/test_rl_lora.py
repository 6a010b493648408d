"""The RL stage with LoRA on the 7B model at reduced width (configs/train/openfly-7b-lora.yaml with
configs/model/reduced-width.yaml, from a synthetic OpenVLA-layout folder, as tests/training/test_shipped_configs.py
trains it): the reference policy is the model with its adapters off (no second copy of the weights) and equals the
starting policy, and a run checkpoints its adapter, resumes after a crash to the uninterrupted run's weights and
merges at the end."""

from __future__ import annotations

import importlib
import os
from pathlib import Path
from unittest import mock

import pytest
import torch
from conftest import REPO_ROOT, reset_accelerate, split_batch, train_main
from safetensors.torch import load_file
from test_rl_stage import rl_logs

from openfly_agent import constants as C
from openfly_agent.model.agent import OpenFlyAgent
from openfly_agent.model.language.lora import merge_lora
from openfly_agent.model.persistence.lora_checkpoint import load_lora_agent, merged_model_of
from openfly_agent.training.config import TrainConfig
from openfly_agent.training.preflight import PreflightError
from openfly_agent.training.rl_loss import k3_kl
from openfly_agent.training.rl_reference import AdaptersOff
from openfly_agent.training.rl_trainer import set_up_rl, taken_log_probs
from openfly_agent.training.stops import STOP_AFTER_STEPS_ENV
from openfly_agent.utils.config import parse_config

LORA_CONFIG = REPO_ROOT / "configs" / "train" / "openfly-7b-lora.yaml"


@pytest.fixture(scope="module")
def synthetic_openvla(tmp_path_factory) -> Path:
    """A reduced-width OpenVLA-layout folder (weights, index, config.json, tokenizer)."""
    writer = importlib.import_module("bench.synthetic_openvla")
    folder = tmp_path_factory.mktemp("openvla") / "openvla-reduced"
    writer.write_synthetic_openvla(folder, "reduced")
    return folder


def lora_rl_args(openvla: Path, dataset: Path, output_dir: Path, *more: str) -> list[str]:
    """The 7B LoRA config as shipped (bf16 autocast, gradient checkpointing, r 32 on every LLM linear layer) at
    reduced width, `--stage=rl` from the OpenVLA folder: 2 updates of 1 episode x 2 rollouts of at most 3 steps,
    one minibatch each (so update 1's KL is the KL at its first minibatch), a checkpoint after each update."""
    writer = importlib.import_module("bench.synthetic_openvla")
    return [
        "--config_path", str(LORA_CONFIG),
        f"--init.checkpoint={openvla}",
        f"--data.root={dataset}",
        f"--model.llm.tokenizer_path={openvla}",
        *writer.reduced_width_args(),
        "--stage=rl", "--steps=2", "--rl.group_size=2", "--rl.episodes_per_update=1", "--rl.max_steps=3",
        "--rl.num_envs=4", "--rl.progress_weight=1.0", "--rl.minibatches=1", "--batch.per_device_batch_size=4",
        "--checkpoint.save_interval=1", "--logging.tracker=none", "--cpu=true",
        f"--output_dir={output_dir}",
        *more,
    ]  # fmt: skip


@pytest.fixture
def lora_run(synthetic_openvla, generated_dataset, tmp_path):
    """`set_up_rl` of the LoRA config (before its first update)."""
    reset_accelerate()
    try:
        yield set_up_rl(
            parse_config(TrainConfig, lora_rl_args(synthetic_openvla, generated_dataset, tmp_path))
        )
    finally:
        reset_accelerate()


def test_the_lora_reference_is_the_model_with_its_adapters_off_and_stays_the_start(lora_run):
    run = lora_run
    agent = run.accelerator.unwrap_model(run.model)
    # no copy of the base weights: the reference holds the starting projector and grounding head only
    assert {name.split(".")[1] for name in run.reference.starting} == {"projector", "grounding_head"}
    trained_outside_adapters = {
        n for n, p in agent.named_parameters() if p.requires_grad and "lora_" not in n
    }
    assert set(run.reference.starting) == trained_outside_adapters
    batch = split_batch(run.cfg, agent, C.SPLIT_TRAIN, [0, 1, 2, 3])

    def log_probs(policy) -> torch.Tensor:
        run.model.eval()
        with torch.no_grad():
            return taken_log_probs(policy, batch, run.action_ids, run.cfg.rl.temperature)["logp"]

    start = log_probs(run.model)
    # update 0: the reference is the starting policy (fresh adapters add B @ A = 0)
    torch.testing.assert_close(log_probs(run.reference), start, rtol=0.0, atol=1e-6)
    assert float(k3_kl(start, log_probs(run.reference)).max()) < 1e-6
    # one optimizer step moves the adapters and the projector; the reference stays the starting policy
    run.optimizer.zero_grad()
    (-taken_log_probs(run.model, batch, run.action_ids, run.cfg.rl.temperature)["logp"].sum()).backward()
    run.optimizer.step()
    lora_b = [p for n, p in agent.named_parameters() if "lora_B" in n]
    assert any(bool(p.detach().any()) for p in lora_b)
    assert float((log_probs(run.model) - start).abs().max()) > 1e-4
    torch.testing.assert_close(log_probs(run.reference), start, rtol=0.0, atol=1e-6)


def test_adapters_that_start_non_zero_are_refused():
    model = torch.nn.ModuleDict({"lora_B": torch.nn.Linear(2, 2, bias=False)})
    torch.nn.init.zeros_(model["lora_B"].weight)
    AdaptersOff(model, model, "gaussian")  # zero: the reference is the starting policy
    torch.nn.init.ones_(model["lora_B"].weight)
    with pytest.raises(PreflightError, match=r"lora\.init=pissa starts 1 of them non-zero"):
        AdaptersOff(model, model, "pissa")


def test_the_7b_lora_rl_stage_checkpoints_resumes_and_merges(
    synthetic_openvla, generated_dataset, tmp_path, capsys
):
    whole, cut = tmp_path / "whole", tmp_path / "cut"
    assert train_main(lora_rl_args(synthetic_openvla, generated_dataset, whole)) == 0
    figures = rl_logs(whole)
    assert sorted(figures) == [1, 2] and all(f["samples_trained"] > 0 for f in figures.values())
    assert figures[1]["kl"] < 1e-6  # one minibatch: the KL before any step, the reference = the start
    assert figures[2]["kl"] > 0  # update 2 starts from the policy update 1 moved
    checkpoints = whole / "checkpoints"
    assert all((checkpoints / f"step-00000{i}" / C.ADAPTER_DIR_NAME).is_dir() for i in (1, 2))
    last = (checkpoints / "last").resolve()
    assert merged_model_of(last) == whole / "merged"  # written after the last checkpoint
    capsys.readouterr()
    # RL from this run: its checkpoints hold the adapter only, so the merged model is named instead (one line)
    again = lora_rl_args(
        synthetic_openvla, generated_dataset, tmp_path / "again", f"--init.checkpoint={whole}"
    )
    assert train_main(again) == 2
    error = capsys.readouterr().err.strip().splitlines()[-1]  # after the log lines
    assert error.startswith(f"train.py: init.checkpoint {whole} is a LoRA checkpoint"), error
    assert f"start stage=rl from {whole / 'merged'}" in error and error.endswith("fresh adapters to them")

    # a run that crashes after the checkpoint of update 1, then resumed, ends with the same adapter and merge
    with mock.patch.dict(os.environ, {STOP_AFTER_STEPS_ENV: "1"}):
        assert train_main(lora_rl_args(synthetic_openvla, generated_dataset, cut)) == 0
    assert not (cut / "checkpoints" / "step-000002").exists() and not (cut / "merged").exists()
    assert train_main(lora_rl_args(synthetic_openvla, generated_dataset, cut, "--resume=true")) == 0
    for name in ("adapter_model.safetensors", "trainables.safetensors"):
        a = load_file(str(cut / "checkpoints" / "last" / C.ADAPTER_DIR_NAME / name))
        b = load_file(str(last / C.ADAPTER_DIR_NAME / name))
        assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a), name
    merged = OpenFlyAgent.from_pretrained(str(whole / "merged")).state_dict()
    resumed = OpenFlyAgent.from_pretrained(str(cut / "merged")).state_dict()
    assert all(torch.equal(merged[k], resumed[k]) for k in merged)

    # the merge is the adapter on its base: the OpenVLA folder + the last checkpoint, merged by peft
    adapter_on_base = merge_lora(load_lora_agent(last, base=synthetic_openvla)).state_dict()
    assert merged.keys() == adapter_on_base.keys()
    for key, tensor in merged.items():
        torch.testing.assert_close(tensor.float(), adapter_on_base[key].float(), rtol=0, atol=1e-6, msg=key)
