"""End to end on the real tiny preset and generated data: learning, checkpoints, resume, reload and act."""

from __future__ import annotations

import itertools
import json
import signal
import subprocess
import time
from unittest import mock

import numpy as np
import pytest
import torch
from conftest import (
    STEPS,
    checkpoint_weights,
    make_config,
    start_script,
    train_args,
    train_in_process,
    train_losses,
)

from openfly_agent import constants as C
from openfly_agent.training import stops
from openfly_agent.training.checkpoint import CheckpointManager
from openfly_agent.training.state import ACCELERATE_STATE_DIR, TRAINER_STATE_NAME
from openfly_agent.utils.processes import communicate_group


def test_a_few_steps_lower_the_loss_on_a_fixed_batch(generated_dataset, tmp_path):
    from openfly_agent.data.collator import NavigationCollator
    from openfly_agent.data.dataset import NavigationStepDataset
    from openfly_agent.data.frames import FrameStore
    from openfly_agent.data.openfly_reader import load_openfly_dataset
    from openfly_agent.model.agent import OpenFlyAgent
    from openfly_agent.model.language.tokenizer import train_bpe_tokenizer
    from openfly_agent.training.optim import make_optimizer

    cfg = make_config(generated_dataset, tmp_path)
    episodes = load_openfly_dataset(generated_dataset, C.SPLIT_TRAIN, cfg.data.reader)
    tokenizer = train_bpe_tokenizer([e.instruction for e in episodes], cfg.tokenizer.train_vocab_size)
    torch.manual_seed(0)
    agent = OpenFlyAgent.from_model_config(cfg.model, tokenizer=tokenizer).train()
    k, s = cfg.model.memory.capacity, cfg.model.keyframes.set_size
    dataset = NavigationStepDataset(
        episodes,
        FrameStore(generated_dataset),
        "keyframes",
        k,
        s,
        keyframe_selector=agent.network.keyframe_selector,
    )
    collate = NavigationCollator(agent.processor, k, s)
    batch = collate([dataset[i] for i in range(0, len(dataset), len(dataset) // 4)][:4])
    optimizer = make_optimizer(agent, lr=1e-3, weight_decay=0.0, betas=(0.9, 0.95))
    losses, action_losses = [], []
    torch.manual_seed(0)  # the box-token jitter
    for _ in range(6):
        loss, logs = agent(batch)
        loss.backward()
        optimizer.step()
        optimizer.zero_grad()
        losses.append(logs["loss"])
        action_losses.append(logs["action_loss"])
    # the action cross-entropy falls on the 4 samples; the total (with the grounding terms) falls at every step
    assert action_losses[-1] < 0.8 * action_losses[0], action_losses
    assert all(b < a for a, b in zip(losses, losses[1:])), losses


BN_STATISTICS = ("running_mean", "running_var", "num_batches_tracked")  # buffers: they change in training


def test_run_writes_checkpoints_in_the_hf_layout(reference_run):
    out, result = reference_run
    manager = CheckpointManager(out, keep_last=5)
    assert [p.name for p in manager.complete_checkpoints()] == ["step-000002", "step-000004"]
    final = manager.latest()
    assert result.checkpoint == final and result.state.step == STEPS
    for name in (
        C.CONFIG_NAME, C.WEIGHTS_NAME, C.ACTION_TOKENIZER_NAME, C.TRAIN_CONFIG_NAME, TRAINER_STATE_NAME,
        "tokenizer.json", "tokenizer_config.json",
    ):  # fmt: skip
        assert (final / name).is_file(), name
    assert (final / ACCELERATE_STATE_DIR / "optimizer.bin").is_file()
    state_keys = checkpoint_weights(
        final / ACCELERATE_STATE_DIR
    ).keys()  # trainable tensors (+ BN statistics)
    frozen_params = [
        k for k in state_keys if k.startswith("vision_backbone.") and not k.endswith(BN_STATISTICS)
    ]
    assert state_keys and not frozen_params
    assert any(k.startswith("vision_backbone.") for k in checkpoint_weights(final))
    assert json.loads((final / C.TRAIN_CONFIG_NAME).read_text())["steps"] == STEPS
    assert sorted(train_losses(out)) == list(range(1, STEPS + 1))
    assert set(result.final_metrics) >= {"action_accuracy", "box_iou", "majority_class_rate", "samples"}
    assert 0.0 <= result.final_metrics["majority_class_rate"] <= 1.0


def test_saved_checkpoint_loads_and_acts(reference_run, generated_dataset):
    from openfly_agent.data.frames import FrameStore
    from openfly_agent.data.openfly_reader import load_openfly_dataset
    from openfly_agent.model.agent import OpenFlyAgent

    out, result = reference_run
    agent = OpenFlyAgent.from_pretrained(str(result.checkpoint)).eval()
    trained = result.agent.state_dict()
    for key, value in agent.state_dict().items():
        torch.testing.assert_close(value, trained[key], rtol=0, atol=0, msg=key)
    episode = load_openfly_dataset(generated_dataset, C.SPLIT_TEST_UNSEEN)[0]
    frames = FrameStore(generated_dataset).frames(episode)
    observations = [
        {
            C.EPISODE_ID: episode.episode_id,
            C.OBS_INSTRUCTION: episode.instruction,
            C.OBS_RGB: frames[t],
            C.OBS_POSE: np.array([*episode.positions[t], episode.yaws[t]]),
        }
        for t in range(2)
    ]
    session = agent.new_session()
    actions = [session.select_action([obs])[0] for obs in observations]
    assert all(a in C.MODEL_ACTION_IDS for a in actions)


def test_stop_mid_run_then_resume_ends_with_identical_weights(reference_run, generated_dataset, tmp_path):
    out, _ = reference_run
    stopped = train_in_process(make_config(generated_dataset, tmp_path, steps=STEPS), stop_after=3)
    assert stopped.stopped_early and stopped.state.step == 3
    assert CheckpointManager(tmp_path, 5).latest().name == "step-000002"  # step 3 was never saved
    resume = make_config(
        generated_dataset, tmp_path, steps=STEPS, resume="true", validation__final_eval="false"
    )
    resumed = train_in_process(resume)
    assert resumed.state.step == STEPS
    expected = checkpoint_weights(out / "checkpoints" / "step-000004")
    found = checkpoint_weights(tmp_path / "checkpoints" / "step-000004")
    assert expected.keys() == found.keys()
    for key in expected:
        torch.testing.assert_close(found[key], expected[key], rtol=0, atol=0, msg=key)
    reference, again = train_losses(out), train_losses(tmp_path)
    assert again == pytest.approx(reference, rel=0, abs=0)


def test_ctrl_c_ends_with_one_line_and_130(generated_dataset, tmp_path):
    """SIGINT (Ctrl-C): no traceback, one line saying how to go on from the last checkpoint, exit code 130."""
    args = train_args(generated_dataset, tmp_path, steps=10_000, checkpoint__save_interval=1)
    with start_script(args, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True) as process:
        deadline = time.monotonic() + 240
        while CheckpointManager(tmp_path, 5).latest() is None:  # a checkpoint to resume from
            assert process.poll() is None, "train.py exited before its first checkpoint"
            assert time.monotonic() < deadline, "no checkpoint within 240 s"
            time.sleep(0.2)
        process.send_signal(signal.SIGINT)
        _, err = communicate_group(process, timeout=120)
    assert process.returncode == 130, err[-3000:]
    assert "Traceback" not in err, err[-3000:]
    last = err.strip().splitlines()[-1]
    assert last.startswith("train.py: interrupted; run the same command with --resume to resume from "), last
    assert str(tmp_path / "checkpoints" / "step-") in last


def test_sigterm_saves_a_checkpoint_and_resume_finishes(generated_dataset, tmp_path):
    """A preemption notice (SIGTERM) ends the run after the current step with a resumable checkpoint."""
    args = train_args(
        generated_dataset, tmp_path, steps=10_000, checkpoint__save_interval=0, validation__final_eval="false"
    )
    metrics = tmp_path / "logs" / "metrics.jsonl"
    with start_script(args) as process:
        deadline = time.monotonic() + 240
        while not (
            metrics.is_file() and train_losses(tmp_path)
        ):  # the first logged step: training is under way
            assert process.poll() is None, "train.py exited before training started"
            assert time.monotonic() < deadline, "no training step logged within 240 s"
            time.sleep(0.5)
        process.send_signal(signal.SIGTERM)
        assert process.wait(timeout=120) == 0
    latest = CheckpointManager(tmp_path, 5).latest()
    assert latest is not None, "no checkpoint after SIGTERM"
    stopped_at = int(latest.name.split("-")[1])
    assert 1 <= stopped_at < 10_000
    assert (latest / "model.safetensors").is_file()
    resume = make_config(
        generated_dataset, tmp_path, steps=stopped_at + 2, resume="true", validation__final_eval="false"
    )
    resumed = train_in_process(resume)
    assert resumed.state.step == stopped_at + 2


def _logged(output_dir, key: str) -> dict[int, float]:
    values = {}
    for line in (output_dir / "logs" / "metrics.jsonl").read_text().splitlines():
        record = json.loads(line)
        if key in record:
            values[record["step"]] = record[key]
    return values


def test_a_time_horizon_decays_the_lr_over_the_time_limit_counted_over_resumes(generated_dataset, tmp_path):
    """optim.horizon=time: a run cut by its time limit ends at the lr floor, and a resume spends what is left."""
    overrides = {
        "steps": 100_000, "time_limit_minutes": 0.05, "optim__horizon": "time", "optim__schedule": "linear",
        "optim__warmup_steps": 0, "optim__min_lr_ratio": 0.0, "checkpoint__save_interval": 0,
        "validation__final_eval": "false",
    }  # fmt: skip
    # the run's clock advances 0.1 s each time it is read, so the 3 s budget lasts the same number of steps
    # however loaded the machine is (a real clock let a slow first step spend the whole budget alone)
    ticks = itertools.count()
    with mock.patch.object(stops, "monotonic_clock", lambda: 0.1 * next(ticks)):
        result = train_in_process(make_config(generated_dataset, tmp_path, **overrides))
    assert result.stopped_early and 3 <= result.state.step < 100_000
    lrs = _logged(tmp_path, "train/lr")
    peak = make_config(generated_dataset, tmp_path, **overrides).optim.lr
    steps = sorted(lrs)  # each step's lr reads the time used up to the step before: the last one is near 0
    assert lrs[steps[-1]] < 0.1 * peak and lrs[steps[0]] == pytest.approx(peak, rel=1e-3)
    assert all(lrs[a] >= lrs[b] for a, b in zip(steps, steps[1:]))  # 100,000 steps alone would hardly decay
    saved = json.loads((CheckpointManager(tmp_path, 5).latest() / TRAINER_STATE_NAME).read_text())
    assert saved["train_seconds"] >= 3
    # the whole budget is spent: a resume with the same limit stops after one step instead of starting over
    with mock.patch.object(stops, "monotonic_clock", lambda: 0.1 * next(ticks)):
        resumed = train_in_process(make_config(generated_dataset, tmp_path, resume="true", **overrides))
    assert resumed.state.step == result.state.step + 1
