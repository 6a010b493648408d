"""Action statistics (OpenVLA format) on a hand-made set, with numbers checked by hand."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from openfly_agent.data.schema import Episode
from openfly_agent.data.stats import action_vectors, compute_action_statistics


def _episode(name: str, actions: list[int]) -> Episode:
    n = len(actions)
    return Episode(
        f"s/astar_data/c/{name}", "s", "x", np.asarray(actions), np.zeros((n, 3)), np.zeros(n), ["f"] * n
    )


def test_statistics_on_hand_made_set():
    # 100 model steps: forward 9 x40, forward 3 x30, turn left x20, ascend x9, stop x1; plus 5 take-off steps
    episodes = [
        _episode("a", [-1] * 5 + [9] * 40 + [2] * 20 + [0]),
        _episode("b", [1] * 30 + [4] * 9),
        _episode("c", [-1, -1]),  # no model step: not a trajectory of the statistics
    ]
    stats = compute_action_statistics(episodes)
    assert stats["num_transitions"] == 100 and stats["num_trajectories"] == 2
    a = stats["action"]
    # dim 0 stop: one 1 in 100 -> mean 0.01; std sqrt(0.01 - 0.0001); the 99th percentile (0.01, linear
    # interpolation between the 99th and 100th sorted values) would clip the 1, so q99 is widened to max = 1.
    assert a["mean"][0] == pytest.approx(0.01) and a["std"][0] == pytest.approx(math.sqrt(0.0099))
    assert (a["q01"][0], a["q99"][0]) == (0.0, 1.0)
    # dim 1 forward metres: 9 x40, 3 x30, 0 x30 -> mean 4.5, E[x^2] = 35.1, std sqrt(14.85); q99 = 9 already
    assert a["mean"][1] == pytest.approx(4.5) and a["std"][1] == pytest.approx(math.sqrt(14.85))
    assert (a["min"][1], a["max"][1], a["q01"][1], a["q99"][1]) == (0.0, 9.0, 0.0, 9.0)
    # dim 2 turn left: 15 x20 -> mean 3; dim 4 up: 2 x9 -> mean 0.18, 99th percentile is 2 without widening
    assert a["mean"][2] == pytest.approx(3.0) and a["q99"][2] == 15.0
    assert a["mean"][4] == pytest.approx(0.18) and a["q99"][4] == 2.0
    # unused dims 3, 5, 6, 7: all zero, q01 == q99 == 0
    for d in (3, 5, 6, 7):
        assert a["mean"][d] == a["std"][d] == a["min"][d] == a["max"][d] == a["q01"][d] == a["q99"][d] == 0.0
    assert a["mask"] == [True] * 8
    assert all(len(a[k]) == 8 for k in ("mean", "std", "max", "min", "q01", "q99", "mask"))


def test_no_model_steps_is_an_error():
    with pytest.raises(ValueError, match="no model actions"):
        compute_action_statistics([_episode("a", [-1, -2])])


def test_action_vectors_reject_phases():
    assert action_vectors([8]).tolist() == [[0, 6, 0, 0, 0, 0, 0, 0]]
    with pytest.raises(ValueError, match="only 0..9"):
        action_vectors([-1])


@settings(max_examples=40, deadline=None)
@given(st.lists(st.integers(0, 9), min_size=1, max_size=400))
def test_every_used_dim_round_trips_through_q01_q99(actions):
    """Normalising with BOUNDS_Q99 and un-normalising gives back every code value that occurs."""
    stats = compute_action_statistics([_episode("a", actions)])["action"]
    q01, q99 = np.asarray(stats["q01"]), np.asarray(stats["q99"])
    vectors = action_vectors(actions).astype(np.float64)  # (N, 8)
    used = vectors.max(axis=0) > 0
    assert np.all(q99[used] > q01[used])
    normed = np.clip(2 * (vectors - q01) / (q99 - q01 + 1e-8) - 1, -1, 1)
    back = np.where(used, 0.5 * (normed + 1) * (q99 - q01) + q01, 0.0)
    np.testing.assert_allclose(back, vectors, atol=1e-6)
