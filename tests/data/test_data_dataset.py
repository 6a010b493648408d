"""NavigationStepDataset: sample counts and memory sets per history mode (scripted keyframe selector)."""

from __future__ import annotations

import numpy as np
import pytest
from data_factories import make_episode, make_frames

from openfly_agent import constants as C
from openfly_agent.data.dataset import NavigationStepDataset
from openfly_agent.data.frames import FrameStore
from openfly_agent.data.writer import OpenFlyDatasetWriter


class ScriptedSelector:
    """Returns fixed sets and records what it was shown."""

    def __init__(self, sets_for_t):
        self.sets_for_t, self.calls = sets_for_t, []

    def select(self, actions, box_areas, t):
        self.calls.append((actions.copy(), None if box_areas is None else list(box_areas), t))
        return self.sets_for_t(t)


@pytest.fixture()
def store(tmp_path):
    episodes = [
        make_episode(
            "embedded-1/astar_data/low_short/a", [-1, 9, 2, 9, 1, 9, 0, -2], seed=1
        ),  # 6 model steps
        make_episode(
            "embedded-1/astar_data/low_short/b", [9, 3, 0], with_boxes=False, seed=2
        ),  # 3 model steps
    ]
    writer = OpenFlyDatasetWriter(tmp_path)
    frames = {}
    for i, episode in enumerate(episodes):
        frames[episode.episode_id] = make_frames(len(episode), seed=20 + i)
        writer.write_episode(episode, frames[episode.episode_id])
    return episodes, FrameStore(tmp_path), frames


def test_one_sample_per_model_step(store):
    episodes, frames, images = store
    dataset = NavigationStepDataset(episodes, frames, "none", capacity=2, set_size=5)
    assert len(dataset) == 9
    steps = [(dataset[i][C.EPISODE_ID][-1], dataset[i][C.STEP_INDEX], dataset[i][C.ACTION]) for i in range(9)]
    assert steps == [("a", 1, 9), ("a", 2, 2), ("a", 3, 9), ("a", 4, 1), ("a", 5, 9), ("a", 6, 0)] + [
        ("b", 0, 9),
        ("b", 1, 3),
        ("b", 2, 0),
    ]
    sample = dataset[2]  # episode a, t = 3
    np.testing.assert_array_equal(sample[C.OBS_RGB], images[episodes[0].episode_id][3])
    assert sample[C.OBS_INSTRUCTION] == episodes[0].instruction and sample[C.MEMORY] == []
    assert sample[C.BOX].dtype == np.float32 and sample[C.BOX_VISIBLE] is False  # odd frames are invisible
    sample = dataset[1]  # t = 2, visible
    assert sample[C.BOX_VISIBLE] is True and np.allclose(sample[C.BOX], episodes[0].boxes[2])
    assert dataset[7][C.BOX_VISIBLE] is False and not dataset[7][C.BOX].any()  # no boxes at all
    with pytest.raises(IndexError):
        dataset[9]


def test_uniform_history(store):
    episodes, frames, images = store
    dataset = NavigationStepDataset(episodes, frames, "uniform", capacity=2, set_size=5)
    assert [dataset.memory_indices(i) for i in range(6)] == [
        [[0]],  # t = 1
        [[0], [1]],  # t = 2
        [[0], [2]],  # t = 3: linspace(0, 2, 2)
        [[0], [3]],
        [[0], [4]],
        [[0], [5]],
    ]
    assert dataset.memory_indices(6) == []  # episode b, t = 0
    three = NavigationStepDataset(episodes, frames, "uniform", capacity=3, set_size=5)
    assert three.memory_indices(4) == [[0], [2], [4]]  # t = 5: linspace(0, 4, 3)
    memory = dataset[3][C.MEMORY]  # t = 4: frames 0 and 3
    np.testing.assert_array_equal(memory[1][0][0], images[episodes[0].episode_id][3])
    assert memory[0][0][2] is True and memory[1][0][2] is False  # frame 0 visible, frame 3 not


def test_random_history_is_reproducible(store):
    episodes, frames, _ = store
    a = NavigationStepDataset(episodes, frames, "random", capacity=2, set_size=5, seed=5)
    b = NavigationStepDataset(episodes, frames, "random", capacity=2, set_size=5, seed=5)
    draws = [a.memory_indices(i) for i in range(len(a))]
    assert draws == [b.memory_indices(i) for i in range(len(b))]
    for i, sets in enumerate(draws):
        t = a.locate(i)[1]
        flat = [j for s in sets for j in s]
        assert len(flat) == min(2, t) and flat == sorted(set(flat)) and all(0 <= j < t for j in flat)
    c = NavigationStepDataset(episodes, frames, "random", capacity=2, set_size=5, seed=6)
    assert [c.memory_indices(i) for i in range(len(c))] != draws  # another seed, other draws
    a.set_epoch(1)
    assert [a.memory_indices(i) for i in range(len(a))] != draws  # another epoch, other draws
    a.set_epoch(0)
    assert [a.memory_indices(i) for i in range(len(a))] == draws


def test_keyframe_history_with_scripted_selector(store):
    episodes, frames, images = store
    selector = ScriptedSelector(lambda t: [[t - 1], [0, 1, 2, 3, 4, 5, 6][:t]] if t >= 2 else [])
    dataset = NavigationStepDataset(
        episodes, frames, "keyframes", capacity=2, set_size=3, keyframe_selector=selector
    )
    # t = 4 of episode a: sets {3} and {0, 1, 2, 3}; sets are sorted oldest first, cut to their last 3 frames
    assert dataset.memory_indices(3) == [[1, 2, 3], [3]]
    actions, areas, t = selector.calls[-1]
    assert t == 4 and actions.tolist() == [-1, 9, 2, 9]  # only the past: the label at t is not shown
    boxes = episodes[0].boxes
    assert areas[1] is None and areas[3] is None  # frames where the landmark is not visible
    np.testing.assert_allclose([areas[0], areas[2]], [boxes[0, 2] * boxes[0, 3], boxes[2, 2] * boxes[2, 3]])
    sample = dataset[3]
    assert [len(s) for s in sample[C.MEMORY]] == [3, 1]
    np.testing.assert_array_equal(sample[C.MEMORY][0][1][0], images[episodes[0].episode_id][2])
    dataset.memory_indices(7)  # episode b (no boxes), t = 1: areas unknown
    assert selector.calls[-1][1] is None and selector.calls[-1][2] == 1


def test_keyframe_history_keeps_the_last_capacity_sets(store):
    episodes, frames, _ = store
    selector = ScriptedSelector(lambda t: [[j] for j in range(t)])
    dataset = NavigationStepDataset(
        episodes, frames, "keyframes", capacity=2, set_size=5, keyframe_selector=selector
    )
    assert dataset.memory_indices(4) == [[3], [4]]  # t = 5


def test_keyframe_selector_must_return_past_frames(store):
    episodes, frames, _ = store
    dataset = NavigationStepDataset(
        episodes,
        frames,
        "keyframes",
        capacity=2,
        set_size=5,
        keyframe_selector=ScriptedSelector(lambda t: [[t]]),
    )
    with pytest.raises(ValueError, match=r"must be in \[0, 2\)"):
        dataset.memory_indices(1)


def test_keyframes_mode_needs_a_selector(store):
    episodes, frames, _ = store
    with pytest.raises(ValueError, match="keyframe_selector"):
        NavigationStepDataset(episodes, frames, "keyframes", capacity=2, set_size=5)
    with pytest.raises(ValueError, match="history='latest'"):
        NavigationStepDataset(episodes, frames, "latest", capacity=2, set_size=5)
