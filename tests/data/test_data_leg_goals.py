"""data/leg_goals.py: each step's leg goal on a chained route, and the auxiliary targets, by hand."""

from __future__ import annotations

import math

import numpy as np
from data_factories import make_episode, make_frames

from openfly_agent import constants as C
from openfly_agent.data.dataset import NavigationStepDataset
from openfly_agent.data.frames import FrameStore
from openfly_agent.data.leg_goals import leg_goal_per_step, leg_goal_targets


def _two_legs():
    """East to (6, 0), turn left, north to (6, 6), STOP: legs end at the step nearest their goal."""
    episode = make_episode("s/t/low_short/0", [1, 1, 2, 1, 1, 0])
    episode.positions = np.array(
        [(0, 0, 30), (3, 0, 30), (6, 0, 30), (6, 0, 30), (6, 3, 30), (6, 6, 30)], float
    )
    episode.yaws = np.array([0.0, 0.0, 0.0, math.pi / 2, math.pi / 2, math.pi / 2])
    episode.landmark_ids = ["b1", "b2"]
    episode.leg_goals = np.array([[6.0, 0.0, 30.0], [6.0, 6.0, 30.0]])
    return episode


def test_leg_zero_ends_at_the_step_nearest_its_goal():
    """Step 2 (at (6, 0)) is leg 1's first decision; without leg goals every step's goal is the last position."""
    episode = _two_legs()
    np.testing.assert_array_equal(leg_goal_per_step(episode), [[6, 0, 30]] * 2 + [[6, 6, 30]] * 4)
    episode.leg_goals = None
    np.testing.assert_array_equal(leg_goal_per_step(episode), [[6, 6, 30]] * 6)


def test_targets_are_the_sine_and_cosine_of_the_bearing_and_the_distance_over_50_m():
    targets = leg_goal_targets(_two_legs())
    assert targets.dtype == np.float32 and targets.shape == (6, 3)
    # steps 0-1: leg 0's goal straight ahead, 6 and 3 m away; step 2: leg 1's goal 6 m, 90 degrees to the left
    # (counter-clockwise positive); steps 3-4: straight ahead; step 5: at the goal (bearing of a zero vector: 0 - yaw)
    np.testing.assert_allclose(targets[:5, 0], [0, 0, 1, 0, 0], atol=1e-6)
    np.testing.assert_allclose(targets[:5, 1], [1, 1, 0, 1, 1], atol=1e-6)
    np.testing.assert_allclose(targets[:, 2], np.array([6, 3, 6, 6, 3, 0]) / 50, atol=1e-6)


def test_the_dataset_gives_each_sample_its_steps_target_only_when_asked(tmp_path):
    from openfly_agent.data.writer import OpenFlyDatasetWriter

    episode = _two_legs()
    OpenFlyDatasetWriter(tmp_path).write_episode(episode, make_frames(len(episode)))
    plain = NavigationStepDataset([episode], FrameStore(tmp_path), "none", capacity=2, set_size=5)
    assert C.LEG_GOAL not in plain[0]
    dataset = NavigationStepDataset([episode], FrameStore(tmp_path), "none", 2, 5, leg_goals=True)
    np.testing.assert_array_equal(dataset[2][C.LEG_GOAL], leg_goal_targets(episode)[2])  # step 2: leg 1
