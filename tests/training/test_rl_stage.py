"""`train.py --stage=rl` end to end on the tiny generated dataset, from the tiny navigation run of conftest.py:
two GRPO updates that log their figures and checkpoint, and a run cut after its first update that, resumed,
ends with the uninterrupted run's weights and figures."""

from __future__ import annotations

import json
import os
from unittest import mock

import pytest
import torch
from conftest import checkpoint_weights, train_args, train_main

from openfly_agent.training.stops import STOP_AFTER_STEPS_ENV

pytestmark = pytest.mark.slow  # a navigation run, then two RL runs of train.py (minutes on a loaded machine)

RL_FIGURES = ("reward", "success_rate", "kl", "entropy", "clip_fraction", "pg_loss", "groups_with_signal")


def rl_args(dataset, reference_run, output_dir, **overrides) -> list[str]:
    """Two updates of 2 episodes x 2 rollouts of at most 6 steps; a progress reward, so groups differ."""
    navigation_run, _ = reference_run
    settings = {
        "stage": "rl",
        "init__checkpoint": str(navigation_run),
        "steps": 2,
        "rl__group_size": 2,
        "rl__episodes_per_update": 2,
        "rl__max_steps": 6,
        "rl__num_envs": 4,
        "rl__progress_weight": 1.0,
        "rl__minibatches": 2,
        "optim__lr": 1e-3,
        "checkpoint__save_interval": 1,
        **overrides,
    }
    return train_args(dataset, output_dir, **settings)


def rl_logs(output_dir) -> dict[int, dict]:
    """step -> the train/ figures of that update (the last record of a step wins, as after a resume)."""
    logs: dict[int, dict] = {}
    for line in (output_dir / "logs" / "metrics.jsonl").read_text().splitlines():
        record = json.loads(line)
        if "train/reward" in record:
            logs[record["step"]] = {
                k[len("train/") :]: v for k, v in record.items() if k.startswith("train/")
            }
    return logs


@pytest.fixture(scope="module")
def rl_run(generated_dataset, reference_run, tmp_path_factory):
    out = tmp_path_factory.mktemp("rl")
    assert train_main(rl_args(generated_dataset, reference_run, out)) == 0
    return out


def test_rl_stage_logs_each_update_and_checkpoints(rl_run, reference_run):
    logs = rl_logs(rl_run)
    assert sorted(logs) == [1, 2]
    for figures in logs.values():
        assert all(name in figures for name in RL_FIGURES), sorted(figures)
        assert 0.0 <= figures["success_rate"] <= 1.0 and figures["kl"] >= 0.0
        assert 0.0 <= figures["clip_fraction"] <= 1.0 and figures["entropy"] > 0.0
    assert logs[1]["groups_with_signal"] > 0  # the progress reward tells every group's flights apart
    config = json.loads((rl_run / "checkpoints" / "last" / "train_config.json").read_text())
    assert config["stage"] == "rl" and config["rl"]["group_size"] == 2
    trained = checkpoint_weights(rl_run / "checkpoints" / "last")
    start = checkpoint_weights(reference_run[0] / "checkpoints" / "last")
    changed = [k for k in start if not torch.equal(start[k], trained[k])]
    assert changed, "the RL updates left every weight as the navigation checkpoint had it"
    assert (rl_run / "checkpoints" / "step-000001").is_dir()


def test_rl_stage_resumed_after_a_crash_ends_as_the_uninterrupted_run(
    rl_run, generated_dataset, reference_run, tmp_path
):
    # the first run stops after update 1 without its final save (a crash after the checkpoint of update 1)
    with mock.patch.dict(os.environ, {STOP_AFTER_STEPS_ENV: "1"}):
        assert train_main(rl_args(generated_dataset, reference_run, tmp_path)) == 0
    assert not (tmp_path / "checkpoints" / "step-000002").exists()
    assert train_main(rl_args(generated_dataset, reference_run, tmp_path, resume="true")) == 0
    resumed, uninterrupted = rl_logs(tmp_path), rl_logs(rl_run)
    assert resumed[2]["reward"] == uninterrupted[2]["reward"]
    assert resumed[2]["kl"] == uninterrupted[2]["kl"]
    a = checkpoint_weights(tmp_path / "checkpoints" / "last")
    b = checkpoint_weights(rl_run / "checkpoints" / "last")
    assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)
