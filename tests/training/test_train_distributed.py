"""Real processes: two gloo processes equal one with the same global batch; SIGKILL mid-run, then resume."""

from __future__ import annotations

import signal
import subprocess
import sys
import time

import pytest
import torch
from conftest import (
    REPO_ROOT,
    STEPS,
    checkpoint_weights,
    make_config,
    run_script,
    train_args,
    train_in_process,
    train_losses,
)

from openfly_agent.training.checkpoint import CheckpointManager


def test_two_processes_give_the_same_losses_and_weights_as_one(reference_run, generated_dataset, tmp_path):
    reference_dir, _, _ = reference_run
    args = train_args(generated_dataset, tmp_path, steps=STEPS, validation__final_eval="false")
    torchrun = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node", "2"]
    done = run_script(args, launcher=torchrun)
    assert done.returncode == 0, done.stderr[-3000:]
    one, two = train_losses(reference_dir), train_losses(tmp_path)
    assert sorted(two) == list(range(1, STEPS + 1))
    assert two == pytest.approx(one, rel=1e-5)
    expected = checkpoint_weights(reference_dir / "checkpoints" / f"step-{STEPS:06d}")
    found = checkpoint_weights(tmp_path / "checkpoints" / f"step-{STEPS:06d}")
    for key in expected:  # float reduction order differs; Adam's 1/sqrt(v) amplifies it on tiny gradients
        torch.testing.assert_close(found[key], expected[key], rtol=1e-4, atol=1e-5, msg=key)


def test_sigkill_mid_run_leaves_a_valid_checkpoint_and_resume_matches(
    reference_run, generated_dataset, tmp_path
):
    reference_dir, _, _ = reference_run
    args = train_args(generated_dataset, tmp_path, steps=STEPS, checkpoint__save_interval=1)
    env_cmd = run_script.__defaults__  # noqa: F841  (the same environment as run_script)
    process = _start(args)
    manager = CheckpointManager(tmp_path, keep_last=5)
    deadline = time.monotonic() + 240
    while manager.latest() is None or manager.latest().name < "step-000002":
        assert process.poll() is None, "training ended before it could be killed"
        assert time.monotonic() < deadline, "no checkpoint appeared"
        time.sleep(0.05)
    process.send_signal(signal.SIGKILL)  # at an arbitrary point after step 2: computing or writing step 3
    process.wait()
    latest = CheckpointManager(tmp_path, keep_last=5).latest()
    assert latest is not None and (latest / "trainer_state.json").is_file()
    _, resumed = train_in_process(
        make_config(generated_dataset, tmp_path, steps=STEPS, resume="true", validation__final_eval="false")
    )
    assert resumed.state.step == STEPS
    assert not any(p.name.startswith(".tmp-") for p in (tmp_path / "checkpoints").iterdir())
    expected = checkpoint_weights(reference_dir / "checkpoints" / f"step-{STEPS:06d}")
    found = checkpoint_weights(tmp_path / "checkpoints" / f"step-{STEPS:06d}")
    for key in expected:
        torch.testing.assert_close(found[key], expected[key], rtol=0, atol=0, msg=key)


def _start(args: list[str]) -> subprocess.Popen:
    import os

    env = {**os.environ, "HF_HUB_OFFLINE": "1", "HF_DATASETS_OFFLINE": "1", "PYTHONPATH": str(REPO_ROOT)}
    return subprocess.Popen(
        [sys.executable, str(REPO_ROOT / "train.py"), *args],
        cwd=REPO_ROOT, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
    )  # fmt: skip
