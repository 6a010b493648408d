"""Keyframe selection on scripted trajectories (turns, climbs, straight flight)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from openfly_agent.model.memory.keyframes import (
    KeyframeSelector,
    candidate_set,
    change_points,
    motion_class,
    motion_classes_from_poses,
)
from openfly_agent.sim.dynamics import rollout_array
from openfly_agent.utils.geometry import Pose

BIG = 0.5  # box area well above theta = 0.25


def test_motion_classes():
    assert [motion_class(a) for a in (1, 8, 9)] == [1, 1, 1]
    assert [motion_class(a, merge_forward=False) for a in (1, 8, 9)] == [1, 8, 9]
    assert motion_class(-1) == 4 and motion_class(-2) == 5


def test_straight_flight_has_no_change_points():
    actions = [1, 9, 9, 8, 1, 9, 9, 9, 8, 1]
    assert change_points(actions) == []
    assert KeyframeSelector().select(actions, [BIG] * len(actions), len(actions)) == []
    # without merging the forward lengths, each length change counts
    assert change_points(actions, merge_forward=False) == [1, 3, 4, 5, 8, 9]


def test_turn_sets_complete_two_frames_later():
    actions = [9, 9, 9, 2, 9, 9, 9, 9, 0]
    assert change_points(actions) == [3, 4, 8]  # 8: forward -> stop
    selector = KeyframeSelector(capacity=2)
    areas = [BIG] * len(actions)
    assert selector.select(actions, areas, 5) == []  # set of c = 3 needs frame 5 to exist (t - 1 >= 5)
    assert selector.select(actions, areas, 6) == [[1, 2, 3, 4, 5]]
    assert selector.select(actions, areas, 7) == [[1, 2, 3, 4, 5], [2, 3, 4, 5, 6]]


def test_climb_and_capacity_keeps_the_latest_sets():
    actions = [1, 1, 4, 4, 4, 1, 1, 1, 3, 1, 1, 1, 1]
    assert change_points(actions) == [2, 5, 8, 9]
    selector = KeyframeSelector(capacity=2)
    areas = [BIG] * len(actions)
    assert selector.completed_sets(actions, 13) == [
        [0, 1, 2, 3, 4],
        [3, 4, 5, 6, 7],
        [6, 7, 8, 9, 10],
        [7, 8, 9, 10, 11],
    ]
    assert selector.select(actions, areas, 13) == [[6, 7, 8, 9, 10], [7, 8, 9, 10, 11]]
    assert KeyframeSelector(capacity=0).select(actions, areas, 13) == []


def test_area_filter_drops_frames_and_empty_sets():
    actions = [1, 1, 2, 1, 1, 1, 1, 1, 3, 1, 1, 1]
    #        frame: 0    1     2    3     4    5     6    7    8    9    10   11
    areas = [0.3, None, 0.1, 0.25, 0.9, 0.2, 0.1, 0.1, 0.1, 0.1, 0.1, 0.1]
    selector = KeyframeSelector(capacity=3, theta=0.25)
    # change points 2, 3, 8, 9; the sets of 8 and 9 have no frame >= 0.25 and are dropped
    assert selector.select(actions, areas, 12) == [[0, 3, 4], [3, 4]]


def test_unknown_boxes_keep_every_candidate():
    actions = [1, 1, 2, 1, 1, 1]
    assert KeyframeSelector().select(actions, None, 6) == [[0, 1, 2, 3, 4], [1, 2, 3, 4, 5]]


def test_candidate_set_clips_at_zero():
    assert candidate_set(1, 2) == [0, 1, 2, 3]


def test_bad_arguments():
    with pytest.raises(ValueError, match="outside the action history"):
        KeyframeSelector().select([1, 2], None, 3)
    with pytest.raises(ValueError, match="fewer than step"):
        KeyframeSelector().select([1, 2, 1], [BIG], 3)
    with pytest.raises(ValueError, match="theta"):
        KeyframeSelector(theta=1.5)


@settings(max_examples=60, deadline=None)
@given(
    actions=st.lists(st.sampled_from([-1, 0, 1, 2, 3, 4, 5, 8, 9]), min_size=1, max_size=40),
    data=st.data(),
)
def test_selection_never_reads_the_future(actions, data):
    t = data.draw(st.integers(0, len(actions)))
    areas = data.draw(
        st.lists(st.one_of(st.none(), st.floats(0, 1)), min_size=len(actions), max_size=len(actions))
    )
    selector = KeyframeSelector(capacity=2)
    sets = selector.select(actions, areas, t)
    assert sets == selector.select(actions[:t], areas[:t], t)  # same answer without the future
    assert len(sets) <= 2
    for frames in sets:
        assert frames == sorted(frames) and all(0 <= f < t for f in frames)
        assert all(areas[f] is not None and areas[f] >= 0.25 for f in frames)


def test_pose_classes_match_the_actions_that_made_them():
    actions = [1, 1, 2, 2, 9, 4, 4, 8, 3, 6, 7, 5, 1]
    poses = rollout_array(Pose(0.0, 0.0, 10.0, 0.3), actions)
    classes = motion_classes_from_poses(poses[: len(actions) + 1])
    assert classes[: len(actions)] == [motion_class(a) for a in actions]
    assert classes[-1] == 0
    assert change_points(classes[: len(actions)]) == change_points(actions)


def test_numpy_histories_are_accepted():
    actions = np.array([9, 9, 9, 2, 9, 9, 9, 9, 0])
    assert KeyframeSelector().select(actions[:7], None, 7) == [[1, 2, 3, 4, 5], [2, 3, 4, 5, 6]]


def test_the_selector_of_a_models_settings():
    from openfly_agent.model.config import KeyframeConfig

    selector = KeyframeSelector.from_config(
        KeyframeConfig(theta=0.1, radius=1, merge_forward=False), capacity=3
    )
    assert selector == KeyframeSelector(capacity=3, theta=0.1, radius=1, merge_forward=False)
    assert selector.set_size == KeyframeConfig(radius=1).set_size == 3
