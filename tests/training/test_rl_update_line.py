"""The RL stage's per-update log line (openfly_agent/training/rl_trainer.py: update_line)."""

from __future__ import annotations

from openfly_agent.training.rl_trainer import update_line


def test_an_update_that_trained_prints_its_kl_entropy_and_clip_fraction():
    logs = {"reward": 0.5625, "success_rate": 0.5625, "groups_with_signal": 0.75, "kl": 0.08904,
            "entropy": 0.5821, "clip_fraction": 0.0}  # fmt: skip
    assert update_line(27, logs) == (
        "update 27: reward 0.562, success 0.562, groups with signal 0.75, kl 0.0890, entropy 0.582, clip 0.000"
    )


def test_an_update_without_signal_says_so_instead_of_printing_nan():
    # 8 groups of 4 flights: 4 groups all succeeded, 4 all failed; no advantage, nothing trained
    logs = {"reward": 0.5, "success_rate": 0.5, "groups_with_signal": 0.0}
    line = update_line(28, logs)
    assert (
        line
        == "update 28: reward 0.500, success 0.500, groups with signal 0.00; no group with signal, the policy is unchanged"
    )
    assert "nan" not in line
