"""bench/analysis/offline_compare.py: the paired held-out accuracy of two runs, with hand-checked numbers."""

from __future__ import annotations

import numpy as np
import pytest

from bench.analysis.offline_compare import StepHits, episode_bootstrap_interval, paired_hits, paired_markdown


def test_the_same_gain_in_every_episode_gives_a_point_interval():
    # two episodes of two steps; B predicts one more step than A in each: +1 of 2 steps, whatever is resampled
    episodes = ["e1", "e1", "e2", "e2"]
    diff, low, high = episode_bootstrap_interval(episodes, np.array([1, 0, 0, 0]), np.array([1, 1, 1, 0]))
    assert (diff, low, high) == (0.5, 0.5, 0.5)


def test_whole_episodes_are_resampled():
    # e1: B right on both steps where A is wrong (gain 2 of 2); e2: no difference. Point: 2 / 4 = 0.5. A resample
    # draws e1 twice (1.0), e2 twice (0.0) or one of each (0.5), with chances 1/4, 1/4, 1/2: the 2.5 and 97.5 %
    # quantiles are 0.0 and 1.0. Steps resampled one by one would not reach 0.0 or 1.0 this often.
    episodes = ["e1", "e1", "e2", "e2"]
    diff, low, high = episode_bootstrap_interval(episodes, np.array([0, 0, 1, 0]), np.array([1, 1, 1, 0]))
    assert diff == 0.5 and low == 0.0 and high == 1.0


def test_identical_runs_differ_by_exactly_nothing():
    hits = np.array([1.0, 0.0, 1.0, 1.0, 0.0])
    assert episode_bootstrap_interval(list("aabbc"), hits, hits.copy()) == (0.0, 0.0, 0.0)


def test_the_interval_is_seeded_and_refuses_misaligned_samples():
    rng = np.random.default_rng(1)
    episodes = [f"e{i // 5}" for i in range(200)]
    a, b = rng.integers(0, 2, 200), rng.integers(0, 2, 200)
    assert episode_bootstrap_interval(episodes, a, b) == episode_bootstrap_interval(episodes, a, b)
    diff, low, high = episode_bootstrap_interval(episodes, a, b)
    assert low <= diff <= high and diff == pytest.approx((b.sum() - a.sum()) / 200)
    with pytest.raises(ValueError, match="aligned"):
        episode_bootstrap_interval(episodes[:-1], a, b)


def _hits(keys, hits):
    return StepHits(keys=keys, hits=np.array(hits, dtype=float), split="test_unseen")


def test_paired_hits_counts_the_steps_only_one_run_predicts():
    keys = [("e1", 0), ("e1", 1), ("e2", 0), ("e2", 1)]
    figures = paired_hits(_hits(keys, [1, 0, 1, 0]), _hits(keys, [1, 1, 0, 1]), resamples=200)
    assert figures["accuracy_a"] == 0.5 and figures["accuracy_b"] == 0.75 and figures["diff"] == 0.25
    assert (figures["only_a"], figures["only_b"], figures["samples"], figures["episodes"]) == (1, 2, 4, 2)
    table = paired_markdown(figures, "current_frame", "keyframes")
    assert "| 50.0 | 75.0 | +25.0 [" in table and "only keyframes right" in table


def test_paired_hits_refuses_other_samples_and_names_the_first():
    a = _hits([("e1", 0), ("e1", 1)], [1, 0])
    with pytest.raises(ValueError, match=r"sample 1 differs: \('e1', 1\) against \('e1', 2\)"):
        paired_hits(a, _hits([("e1", 0), ("e1", 2)], [1, 0]))
    with pytest.raises(ValueError, match="2 and 1 samples"):
        paired_hits(a, _hits([("e1", 0)], [1]))
