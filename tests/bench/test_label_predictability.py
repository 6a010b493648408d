"""Label-predictability probes: hand-checked features and a probe that must find a planted rule."""

from __future__ import annotations

import math

import numpy as np
import pytest

from bench.analysis.label_predictability import (
    FEATURE_NAMES,
    leg_goal_per_step,
    majority_rate,
    run_probes,
    step_features,
)
from openfly_agent.data.schema import Episode


def _episode(episode_id: str, positions, yaws, actions, boxes=None, visible=None) -> Episode:
    n = len(actions)
    return Episode(
        episode_id=episode_id,
        scene_id=episode_id.split("/")[0],
        instruction="fly to the red tower",
        actions=np.asarray(actions),
        positions=np.asarray(positions, dtype=np.float64),
        yaws=np.asarray(yaws, dtype=np.float64),
        frame_ids=[f"f{t}" for t in range(n)],
        split="train",
        category=episode_id.split("/")[2],
        pitch_deg=0.0,
        boxes=None if boxes is None else np.asarray(boxes, dtype=np.float64),
        box_visible=None if visible is None else np.asarray(visible, dtype=bool),
        landmark_ids=["b1"],
    )


def test_step_features_by_hand():
    # forward 3 m east, turn left, forward 3 m north, stop: the goal is the last position (3, 3, 30)
    episode = _episode(
        "s/t/low_short/0",
        positions=[(0, 0, 30), (3, 0, 30), (3, 0, 30), (3, 3, 30)],
        yaws=[0.0, 0.0, math.pi / 2, math.pi / 2],
        actions=[1, 2, 1, 0],
        boxes=[(0.5, 0.5, 0.2, 0.4), (0, 0, 0, 0), (0.25, 0.5, 0.5, 0.5), (0.5, 0.5, 1.0, 1.0)],
        visible=[True, False, True, True],
    )
    f = step_features(episode)
    col = {name: f[:, i] for i, name in enumerate(FEATURE_NAMES)}
    np.testing.assert_allclose(col["goal_distance"], np.array([math.sqrt(18), 3, 3, 0]) / 50, atol=1e-6)
    # goal 45 deg to the left, then 90 deg to the left, then straight ahead (left turns are positive)
    np.testing.assert_allclose(col["goal_bearing"][:3], [math.pi / 4, math.pi / 2, 0.0], atol=1e-6)
    np.testing.assert_allclose(col["visible"], [1, 0, 1, 1])
    np.testing.assert_allclose(col["area"], [0.08, 0.0, 0.25, 1.0], atol=1e-6)
    np.testing.assert_allclose(col["cx"], [0.5, 0.0, 0.25, 0.5], atol=1e-6)
    np.testing.assert_allclose(col["altitude"], [0.6] * 4, atol=1e-6)
    np.testing.assert_allclose(col["step"], [0, 0.05, 0.1, 0.15], atol=1e-6)
    np.testing.assert_allclose(col["previous_action"], [0, 0.2, 0.3, 0.2], atol=1e-6)


def test_majority_rate():
    assert majority_rate(np.array([9, 9, 1, 2]), np.array([9, 1, 1, 1])) == (9, 0.25)


def _planted(seed: int, count: int) -> list[Episode]:
    """Episodes whose action is a function of the goal bearing: left if > 0.3 rad, right if < -0.3, else forward."""
    rng = np.random.default_rng(seed)
    episodes = []
    for i in range(count):
        n = 12
        positions = np.column_stack([rng.uniform(-40, 40, n), rng.uniform(-40, 40, n), np.full(n, 30.0)])
        positions[-1] = (0.0, 0.0, 30.0)
        yaws = rng.uniform(-math.pi, math.pi, n)
        bearing = (np.arctan2(-positions[:, 1], -positions[:, 0]) - yaws + math.pi) % (2 * math.pi) - math.pi
        actions = np.where(bearing > 0.3, 2, np.where(bearing < -0.3, 3, 1))
        actions[-1] = 0
        episodes.append(_episode(f"s/{i}/low_short/{seed}", positions, yaws, actions))
    return episodes


@pytest.mark.parametrize("epochs", [30])
def test_goal_probe_finds_a_planted_rule_the_box_probe_cannot(epochs):
    (majority, rate), probes = run_probes(_planted(0, 120), _planted(1, 40), epochs=epochs)
    by_name = {p.name: p for p in probes}
    goal = by_name["goal distance + bearing (perfect localisation)"]
    box = by_name["target box (perfect grounding)"]
    assert goal.test_accuracy > 0.9 > rate  # the rule is learnable from the bearing
    assert box.test_accuracy < rate + 0.05  # no boxes: nothing beyond the majority class


def test_leg_goal_features_follow_each_legs_goal_by_hand():
    """Two legs: east to (6, 0), then north to (6, 6). Leg 0 ends at the step nearest its goal (step 2, which is
    leg 1's first decision); without leg goals every step's leg goal is the last position."""
    positions = [(0, 0, 30), (3, 0, 30), (6, 0, 30), (6, 0, 30), (6, 3, 30), (6, 6, 30)]
    yaws = [0.0, 0.0, 0.0, math.pi / 2, math.pi / 2, math.pi / 2]
    episode = _episode("s/t/low_short/0", positions, yaws, [1, 1, 2, 1, 1, 0])
    episode.landmark_ids = ["b1", "b2"]
    episode.leg_goals = np.array([[6.0, 0.0, 30.0], [6.0, 6.0, 30.0]])
    np.testing.assert_array_equal(leg_goal_per_step(episode), [[6, 0, 30]] * 2 + [[6, 6, 30]] * 4)
    col = {name: step_features(episode)[:, i] for i, name in enumerate(FEATURE_NAMES)}
    np.testing.assert_allclose(col["leg_goal_distance"], np.array([6, 3, 6, 6, 3, 0]) / 50, atol=1e-6)
    # leg 0's goal straight ahead; at step 2 leg 1's goal is 90 deg to the left, then straight ahead
    np.testing.assert_allclose(col["leg_goal_bearing"][:5], [0, 0, math.pi / 2, 0, 0], atol=1e-6)
    episode.leg_goals = None
    np.testing.assert_array_equal(leg_goal_per_step(episode), [[6, 6, 30]] * 6)
    np.testing.assert_allclose(
        col["goal_distance"][:2], np.array([math.sqrt(72), math.sqrt(45)]) / 50, atol=1e-6
    )
