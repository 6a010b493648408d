"""bench/rl_rollouts.py: its rates from the RL stage's own phase times (hand-checked), and one timed update of
the tiny preset on the training tests' dataset from their navigation run."""

from __future__ import annotations

import argparse

import pytest
from conftest import reset_accelerate

from bench.rl_rollouts import main as bench_main
from bench.rl_rollouts import summary, update_figures

SIZES = argparse.Namespace(episodes=2, group_size=2, max_steps=20, num_envs=4)


def test_an_updates_rates_are_its_steps_and_rollouts_over_its_rollout_time():
    logs = {"rollout_steps": 30.0, "rollout_s": 4.0, "update_s": 11.0, "samples_trained": 12.0}
    figures = update_figures(logs, rollouts=4)
    assert (figures["rollout_steps_per_s"], figures["rollouts_per_s"]) == (7.5, 1.0)
    assert (figures["rollout_steps"], figures["samples_trained"]) == (30, 12)


def test_the_summary_rates_are_over_the_summed_phase_times():
    timed = [
        {"rollouts": 4, "rollout_steps": 30, "rollout_s": 3.0, "update_s": 7.0, "samples_trained": 30},
        {"rollouts": 4, "rollout_steps": 10, "rollout_s": 1.0, "update_s": 9.0, "samples_trained": 5},
    ]
    figures = summary(timed, SIZES, "64x64")
    # 40 steps and 8 rollouts in 4 s of rollouts; (4 + 16) s over 2 updates
    assert (figures["rollout_steps"], figures["samples_trained"]) == (40, 35)
    assert (figures["rollout_steps_per_s"], figures["rollouts_per_s"]) == (10.0, 2.0)
    assert (figures["rollout_s_per_update"], figures["update_s_per_update"], figures["s_per_update"]) == (
        2.0,
        8.0,
        10.0,
    )
    assert figures["markdown"].startswith(
        "| tiny, 64x64, 2 x 2 rollouts of <= 20 steps, 4 envs | 2 | 10.0 | 2.0 | 2.0 + 8.0 = 10.0 |"
    )


@pytest.mark.slow  # the training tests' navigation run, then one RL update
def test_the_bench_times_an_update_of_the_tiny_preset(generated_dataset, reference_run):
    navigation_run, _ = reference_run
    args = ["--dataset_root", str(generated_dataset), "--checkpoint", str(navigation_run)]
    args += ["--updates", "1", "--warmup", "0", "--episodes", "2", "--group_size", "2", "--max_steps", "3"]
    reset_accelerate()
    try:
        *timed, figures = bench_main([*args, "--num_envs", "2"])
    finally:
        reset_accelerate()
    assert len(timed) == 1 and timed[0]["update"] == 1 and timed[0]["rollouts"] == 4
    # 4 flights of 1 to 3 actions each (a flight ends at its STOP, a collision or rl.max_steps)
    assert 4 <= timed[0]["rollout_steps"] <= 12
    # the progress reward tells the flights of a group apart, so the update trains on its steps
    assert timed[0]["samples_trained"] > 0 and timed[0]["rollout_s"] > 0 and timed[0]["update_s"] > 0
    assert figures["summary"] and figures["rollout_steps"] == timed[0]["rollout_steps"]
    assert figures["markdown"].startswith("| tiny, 64x64, 2 x 2 rollouts of <= 3 steps, 2 envs | 1 |")


@pytest.mark.slow  # generates its dataset and trains its navigation run, then one RL update
def test_the_bench_makes_its_dataset_and_agent_when_given_none():
    args = ["--nav_steps", "1", "--updates", "1", "--warmup", "0", "--max_steps", "3", "--num_envs", "2"]
    reset_accelerate()
    try:
        *timed, figures = bench_main(args)
    finally:
        reset_accelerate()
    assert len(timed) == 1 and timed[0]["rollouts"] == 4  # the defaults: 2 episodes x 2 rollouts
    assert 4 <= timed[0]["rollout_steps"] <= 12
    assert figures["markdown"].startswith("| tiny, 64x64, 2 x 2 rollouts of <= 3 steps, 2 envs | 1 |")
