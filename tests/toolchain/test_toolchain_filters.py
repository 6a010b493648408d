"""Quality filters: action count, damaged frames, flying below tree height."""

from __future__ import annotations

import numpy as np

from openfly_agent.toolchain import filters
from openfly_agent.toolchain.config import FilterConfig

CFG = FilterConfig(min_actions=2, max_actions=150)


def test_action_count_bounds():
    assert filters.check_action_count(np.zeros(1), CFG) == filters.REASON_TOO_SHORT
    assert filters.check_action_count(np.zeros(2), CFG) is None
    assert filters.check_action_count(np.zeros(150), CFG) is None
    assert filters.check_action_count(np.zeros(151), CFG) == filters.REASON_TOO_LONG


def test_damaged_frames():
    rng = np.random.default_rng(0)
    good = rng.integers(0, 255, (64, 64, 3), dtype=np.uint8)
    black = np.zeros((64, 64, 3), np.uint8)
    almost_flat = np.full((64, 64, 3), 120, np.uint8)
    almost_flat[:2] = 255  # std ~23 > 3, but one colour covers 15 of 16 rows of the 4x subsampled frame
    assert not filters.is_damaged_frame(good, CFG)
    assert filters.is_damaged_frame(black, CFG)
    assert filters.is_damaged_frame(almost_flat, FilterConfig(max_dominant_fraction=0.93))
    assert not filters.is_damaged_frame(almost_flat, FilterConfig(max_dominant_fraction=0.95))
    assert filters.is_damaged_frame(np.zeros((64, 64), np.uint8), CFG)  # not RGB
    assert filters.check_frames([good, good], CFG) is None
    assert filters.check_frames([good, black], CFG) == filters.REASON_DAMAGED


def test_height_filter_ignores_takeoff_and_landing():
    actions = np.array([-1, -1, 9, 0, -2, -2])
    positions = np.array([[0, 0, 2.0], [0, 0, 5.0], [0, 0, 8.0], [9, 0, 8.0], [9, 0, 8.0], [9, 0, 5.0]])
    assert filters.check_height(positions, actions, ground_z=0.0, tree_height_m=8.0) is None
    assert filters.check_height(positions, actions, ground_z=0.0, tree_height_m=8.5) == filters.REASON_LOW
    assert filters.check_height(positions, actions, ground_z=-1.0, tree_height_m=8.5) is None
