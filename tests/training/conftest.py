"""Fixtures of the training tests: a real generated dataset, train configs and in-process runs."""

from __future__ import annotations

import importlib.util
import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from openfly_agent.utils.processes import run_group, running

REPO_ROOT = Path(__file__).resolve().parents[2]
TINY_DATASET_YAML = Path(__file__).with_name("tiny_dataset.yaml")
HOLD_PROBE = REPO_ROOT / "tests" / "hold_probe.py"
STEPS = 4  # optimizer steps of the reference run (global batch 4 = 2 micro-batches of 2)


@pytest.fixture(scope="session")
def generated_dataset(tmp_path_factory) -> Path:
    """A dataset root written by the toolchain from embedded cities (train / test_seen / test_unseen)."""
    from openfly_agent.toolchain.config import GenerateConfig
    from openfly_agent.toolchain.generate import generate
    from openfly_agent.utils.config import load_yaml_config

    root = tmp_path_factory.mktemp("dataset") / "tiny"
    cfg = load_yaml_config(GenerateConfig, TINY_DATASET_YAML, [f"--output_dir={root}"])
    summary = generate(cfg, progress=False)
    assert all(summary["per_split"].get(split, 0) > 0 for split in ("train", "test_seen", "test_unseen"))
    return root


@pytest.fixture(scope="session")
def reference_run(generated_dataset, tmp_path_factory):
    """An uninterrupted in-process run of STEPS steps, a checkpoint every 2: (output_dir, TrainResult).

    The vision backbone is frozen, so resuming must rebuild frozen weights and restore only trainable ones.
    """
    out = tmp_path_factory.mktemp("reference")
    return out, train_in_process(make_config(generated_dataset, out, steps=STEPS))


def train_args(dataset: Path, output_dir: Path, **overrides) -> list[str]:
    """Command-line overrides of configs/train/tiny.yaml for a test run (small batches, no TensorBoard)."""
    args = {
        "data.root": str(dataset),
        "output_dir": str(output_dir),
        "steps": 4,
        "batch.global_batch_size": 4,
        "batch.per_device_batch_size": 2,
        "optim.warmup_steps": 1,
        "logging.tracker": "none",
        "logging.log_interval": 1,
        "validation.interval": 0,
        "validation.final_max_samples": 8,
        "validation.per_device_batch_size": 4,
        "checkpoint.save_interval": 2,
        "checkpoint.keep_last": 5,
        "freeze_stage": "frozen_vision",
        # bit-exact comparisons (resume, kill, two processes vs one) hold on the CPU; on an H200 four of them
        # failed with CUDA (tests/model/test_model_cuda.py is where the GPU path is tested)
        "cpu": "true",
    }
    args.update({k.replace("__", "."): v for k, v in overrides.items()})
    return ["--config_path", str(REPO_ROOT / "configs/train/tiny.yaml")] + [
        f"--{k}={v}" for k, v in args.items()
    ]


def make_config(dataset: Path, output_dir: Path, **overrides):
    """The `TrainConfig` of `train_args` (use `a__b=value` for `--a.b=value`)."""
    from openfly_agent.training.config import TrainConfig
    from openfly_agent.utils.config import parse_config

    return parse_config(TrainConfig, train_args(dataset, output_dir, **overrides))


def reset_accelerate() -> None:
    """Forget accelerate's process-wide singletons so the next run starts clean (in-process runs only)."""
    from accelerate.state import AcceleratorState, GradientState

    AcceleratorState._reset_state(reset_partial_state=True)
    GradientState._reset_state()


def train_in_process(cfg, stop_after: int | None = None):
    """`training.train(cfg)` in this process; returns its `TrainResult`. `stop_after`: the test-only stop
    (`OPENFLY_STOP_AFTER_STEPS`, training/stops.py): exit after that step without the final save, as a crash."""
    from unittest import mock

    from openfly_agent.training.stops import STOP_AFTER_STEPS_ENV
    from openfly_agent.training.trainer import train

    env = {} if stop_after is None else {STOP_AFTER_STEPS_ENV: str(stop_after)}
    reset_accelerate()
    try:
        with mock.patch.dict(os.environ, env):
            return train(cfg)
    finally:
        reset_accelerate()


def with_val_split(cfg):
    """`cfg` with the validation split a run reads (`val`, or test_seen on a dataset without one), as `train()`
    resolves it first: the tests' tiny datasets have no val routes."""
    import dataclasses

    from openfly_agent.training.preflight import resolve_val_split

    return dataclasses.replace(cfg, data=resolve_val_split(cfg.data)[0])


def built_agent(cfg):
    """The agent a run of `cfg` would start training (checks, tokenizer, init weights, freeze / LoRA applied)."""
    from openfly_agent.training.accelerator import make_accelerator
    from openfly_agent.training.builder import load_splits, prepare_agent

    cfg = with_val_split(cfg)
    reset_accelerate()
    try:
        return prepare_agent(cfg, load_splits(cfg.data, cfg.model.grounding), make_accelerator(cfg), None)
    finally:
        reset_accelerate()


def split_batch(cfg, agent, split: str, indices) -> dict:
    """A collated batch of samples `indices` of `split`, built as the run of `cfg` builds it."""
    from openfly_agent.data.collator import NavigationCollator
    from openfly_agent.training.builder import load_splits

    cfg = with_val_split(cfg)
    dataset = load_splits(cfg.data, cfg.model.grounding).dataset(split, cfg, agent)
    collate = NavigationCollator(agent.processor, cfg.model.memory.capacity, cfg.model.keyframes.set_size)
    return collate([dataset[i] for i in indices])


def _script_env() -> dict[str, str]:
    env = {**os.environ, "HF_HUB_OFFLINE": "1", "HF_DATASETS_OFFLINE": "1", "TOKENIZERS_PARALLELISM": "false"}
    env["PYTHONPATH"] = os.pathsep.join([str(REPO_ROOT), env.get("PYTHONPATH", "")])
    return env


def run_script(args: list[str], launcher: list[str] | None = None, timeout: float = 300, script=None):
    """Run train.py (or `script`) to the end in a subprocess, optionally under a launcher such as torchrun; on
    timeout every process it started is killed (utils/processes.py)."""
    command = (launcher or [sys.executable]) + [str(script or REPO_ROOT / "train.py"), *args]
    return run_group(command, timeout=timeout, cwd=REPO_ROOT, env=_script_env())


def default_sigint() -> None:
    """Child pre-exec: SIGINT back to its default. A shell starts background jobs (`pytest ... &`) with SIGINT
    ignored and children inherit that, so a Ctrl-C test would otherwise depend on how pytest was started."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def start_script(args: list[str], hold: str | None = None, **popen_kwargs):
    """`with start_script(args) as process:` train.py in a subprocess (output discarded unless redirected),
    stopped with everything it started when the block ends. `hold`: run it under tests/hold_probe.py, held
    there (e.g. "final-eval") until a signal."""
    probe = [] if hold is None else [str(HOLD_PROBE), hold]
    command = [sys.executable, *probe, str(REPO_ROOT / "train.py"), *args]
    popen_kwargs.setdefault("stdout", subprocess.DEVNULL)
    popen_kwargs.setdefault("stderr", subprocess.DEVNULL)
    popen_kwargs.setdefault("preexec_fn", default_sigint)
    return running(command, cwd=REPO_ROOT, env=_script_env(), **popen_kwargs)


def train_losses(output_dir: Path) -> dict[int, float]:
    """step -> train/loss from a run's metrics.jsonl (the last record of a step wins, as after a resume)."""
    losses = {}
    for line in (Path(output_dir) / "logs" / "metrics.jsonl").read_text().splitlines():
        record = json.loads(line)
        if "train/loss" in record:
            losses[record["step"]] = record["train/loss"]
    return losses


def checkpoint_weights(folder: Path) -> dict:
    from safetensors.torch import load_file

    return load_file(str(Path(folder) / "model.safetensors"))


def train_main(argv: list[str]) -> int:
    """`train.py`'s `main(argv)` in this process (its exit code), with accelerate's singletons reset around it."""
    spec = importlib.util.spec_from_file_location("train_entry_point", REPO_ROOT / "train.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    reset_accelerate()
    try:
        return module.main(argv)
    finally:
        reset_accelerate()
