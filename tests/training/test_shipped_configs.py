"""Every shipped train config runs through train.py, as users launch it; the 7B ones at reduced width.

Reduced width is configs/model/reduced-width.yaml laid over the model (`--model=<file>`, bench/synthetic_openvla.py's
`reduced_width_args()`): the 7B model's classes (timm DINOv2-with-registers and SigLIP ViTs, a Llama decoder, the
fused projector) at small width, every other
model setting as shipped (the regression grounding head, the discrete head, keyframes + merging, LoRA on every
linear layer, gradient checkpointing). The 7B runs start from an OpenVLA-layout folder written by that module
(sharded safetensors + index, config.json, tokenizer files). Each run is also shortened by `RUN_LENGTH` (steps,
batch, loader workers, final test samples, checkpoint interval): how long it runs, not what it runs.
"""

from __future__ import annotations

import importlib
import json
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from conftest import REPO_ROOT, _script_env, run_script

from openfly_agent.utils.processes import run_group

CONFIGS = REPO_ROOT / "configs" / "train"
RUN_LENGTH = [
    "--steps=2",
    "--batch.global_batch_size=4",
    "--batch.per_device_batch_size=2",
    "--data.num_workers=0",
    "--validation.final_max_samples=8",
    "--checkpoint.save_interval=2",
]
# the tiny configs (the ablations share one representative: they differ in history and memory only)
TINY_CONFIGS = ["tiny.yaml", "tiny-recipe.yaml", "ablations/uniform_history.yaml"]


@pytest.fixture(scope="module")
def synthetic_openvla(tmp_path_factory) -> Path:
    """A reduced-width OpenVLA-layout folder (weights, index, config.json, tokenizer)."""
    writer = importlib.import_module("bench.synthetic_openvla")
    folder = tmp_path_factory.mktemp("openvla") / "openvla-reduced"
    summary = writer.write_synthetic_openvla(folder, "reduced")
    assert summary["shards"] == 3 and (folder / "model.safetensors.index.json").is_file()
    return folder


def seven_b_args(config: str, openvla: Path, dataset: Path, output_dir: Path) -> list[str]:
    """The README's 7B command (init checkpoint, data root, tokenizer) at reduced width and run length."""
    writer = importlib.import_module("bench.synthetic_openvla")
    return [
        "--config_path",
        str(CONFIGS / config),
        f"--init.checkpoint={openvla}",
        f"--data.root={dataset}",
        f"--model.llm.tokenizer_path={openvla}",
        *writer.reduced_width_args(),
        *RUN_LENGTH,
        f"--output_dir={output_dir}",
    ]


def _ok(result) -> str:
    """The output of a finished command, which must have exited 0."""
    output = result.stdout + result.stderr
    assert result.returncode == 0, output[-3000:]
    return output


def _run_module(args: list[str], timeout: float = 300) -> subprocess.CompletedProcess:
    return run_group([sys.executable, *args], timeout=timeout, cwd=REPO_ROOT, env=_script_env())


def test_the_7b_lora_config_trains_resumes_merges_evaluates_and_releases(
    synthetic_openvla, generated_dataset, tmp_path
):
    run = tmp_path / "lora"
    args = seven_b_args("openfly-7b-lora.yaml", synthetic_openvla, generated_dataset, run)
    output = _ok(run_script(args, timeout=600))
    # every tensor by name: the agent's loaded, the new modules initialised, the ViT parts it prunes unused
    assert re.search(
        r"initialised from the OpenVLA checkpoint .*: loaded \d+ tensors, \d+ new, [1-9]\d* unused", output
    )
    assert (run / "checkpoints" / "step-000002" / "adapter").is_dir() and (run / "merged").is_dir()

    output = _ok(run_script([*args, "--resume=true", "--steps=3"], timeout=600))
    assert "starting at step 2" in output  # the merge below is the resumed run's (eval takes it when newer)
    assert (run / "checkpoints" / "last").resolve().name == "step-000003"

    evaluation = tmp_path / "eval"
    output = _ok(
        _run_module(
            [
                "eval.py",
                f"--checkpoint={run}",
                "--sim.type=embedded",
                f"--dataset_root={generated_dataset}",
                "--split=[test_unseen]",
                "--max_episodes=2",
                f"--output_dir={evaluation}",
                "--plots=0",
                "--progress=false",
            ]
        )
    )
    assert f"loaded the LoRA run's merged model {run / 'merged'}" in output
    episodes = (evaluation / "agent" / "episodes.jsonl").read_text().splitlines()
    records = [json.loads(line) for line in episodes]
    assert len(records) == 2 and all(r["error"] is None and r["actions"] for r in records)

    release = tmp_path / "release"
    output = _ok(
        _run_module(
            [
                "-m",
                "openfly_agent.hub",
                "release",
                "--checkpoint",
                str(run),
                "--repo_id",
                "me/openfly-7b-lora-reduced",
                "--output_dir",
                str(release),
            ]
        )
    )
    assert "the LoRA run's merged model" in output
    from openfly_agent.model.agent import OpenFlyAgent
    from openfly_agent.model.grounding.head import BoxRegressionHead

    agent = OpenFlyAgent.from_pretrained(str(release)).eval()
    merged = OpenFlyAgent.from_pretrained(str(run / "merged"))
    assert isinstance(agent.network.grounding_head, BoxRegressionHead)
    for name, tensor in merged.state_dict().items():
        assert torch.equal(agent.state_dict()[name], tensor), name


def test_the_7b_full_config_trains_from_openvla_weights(synthetic_openvla, generated_dataset, tmp_path):
    run = tmp_path / "full"
    args = seven_b_args("openfly-7b-full.yaml", synthetic_openvla, generated_dataset, run)
    output = _ok(run_script(args, timeout=600))
    assert "initialised from the OpenVLA checkpoint" in output
    assert (run / "checkpoints" / "step-000002" / "model.safetensors").is_file()


@pytest.mark.parametrize("config", TINY_CONFIGS)
def test_a_tiny_config_trains_two_steps(config, generated_dataset, tmp_path):
    args = ["--config_path", str(CONFIGS / config), f"--data.root={generated_dataset}", *RUN_LENGTH]
    _ok(run_script([*args, f"--output_dir={tmp_path / 'run'}"], timeout=300))
    assert (tmp_path / "run" / "checkpoints" / "step-000002" / "model.safetensors").is_file()


def test_a_missing_released_dataset_points_to_its_data_card(tmp_path):
    command = [
        sys.executable,
        str(REPO_ROOT / "train.py"),
        "--config_path",
        str(CONFIGS / "openfly-7b-lora.yaml"),
        f"--data.root={tmp_path / 'OpenFly'}",
        f"--output_dir={tmp_path / 'run'}",
    ]
    # one line, from rank 0 (the other ranks of a launch leave it to rank 0: test_train_one_line_errors.py)
    result = run_group(command, timeout=120, cwd=REPO_ROOT, env=_script_env())
    assert result.returncode == 2
    assert result.stderr.count("\n") == 1, result.stderr
    assert "data_cards/openfly_released.md" in result.stderr
    assert os.fspath(tmp_path / "OpenFly") in result.stderr
