"""memory_occupancy: sets and frames per sample of each history mode, counted by hand on two short episodes."""

from __future__ import annotations

import pytest
from data_factories import make_episode, make_frames

from bench.analysis.memory_occupancy import memory_occupancy
from openfly_agent.data.dataset import NavigationStepDataset
from openfly_agent.data.frames import FrameStore
from openfly_agent.data.writer import OpenFlyDatasetWriter


class EvenStepSelector:
    """A keyframe set of the previous frame at every even step, none otherwise."""

    def select(self, actions, box_areas, t):
        return [[t - 1]] if t % 2 == 0 else []


def dataset_of(episodes, frames):
    return NavigationStepDataset(episodes, frames, "uniform", capacity=2, set_size=5)


@pytest.fixture()
def store(tmp_path):
    episodes = [
        make_episode("embedded-1/astar_data/low_short/a", [-1, 9, 2, 9, 1, 9, 0, -2], seed=1),  # t = 1..6
        make_episode("embedded-1/astar_data/low_short/b", [9, 3, 0], seed=2),  # t = 0..2
    ]
    writer = OpenFlyDatasetWriter(tmp_path)
    for i, episode in enumerate(episodes):
        writer.write_episode(episode, make_frames(len(episode), seed=20 + i))
    return episodes, FrameStore(tmp_path)


def test_uniform_history_fills_the_memory_from_the_second_step(store):
    episodes, frames = store
    occupancy = memory_occupancy(dataset_of(episodes, frames))
    # a: 1 set at t = 1, 2 sets at t = 2..6 (11); b: 0, 1, 2 sets at t = 0, 1, 2 (3); one frame per set
    assert occupancy.history == "uniform" and occupancy.samples == 9
    assert occupancy.sets_per_sample == pytest.approx(14 / 9)
    assert occupancy.frames_per_sample == pytest.approx(14 / 9)
    assert occupancy.without_memory == pytest.approx(1 / 9)
    assert occupancy.set_count_fractions == pytest.approx((1 / 9, 2 / 9, 6 / 9))
    # steps to the last step (a: t = 6, b: t = 2) of the 8 samples with memory: 5, 4, 3, 2, 1, 0 and 1, 0
    assert occupancy.episodes_with_memory == 1.0
    assert occupancy.steps_to_end_median == pytest.approx(1.5)
    assert occupancy.near_end_fraction == pytest.approx(7 / 8)
    assert memory_occupancy(dataset_of(episodes, frames), near_end=2).near_end_fraction == pytest.approx(
        4 / 8
    )


def test_keyframes_count_only_the_selected_sets(store):
    episodes, frames = store
    dataset = NavigationStepDataset(
        episodes, frames, "keyframes", capacity=2, set_size=5, keyframe_selector=EvenStepSelector()
    )
    occupancy = memory_occupancy(dataset)
    # one set at t = 2, 4, 6 of a and t = 2 of b: 4 sets of one frame over 9 samples
    assert occupancy.sets_per_sample == pytest.approx(4 / 9)
    assert occupancy.frames_per_sample == pytest.approx(4 / 9)
    assert occupancy.without_memory == pytest.approx(5 / 9)
    assert occupancy.set_count_fractions == pytest.approx((5 / 9, 4 / 9, 0.0))
    # steps to the last step of the samples with memory: 4, 2, 0 (a) and 0 (b)
    assert occupancy.episodes_with_memory == 1.0
    assert occupancy.steps_to_end_median == pytest.approx(1.0)
    assert occupancy.near_end_fraction == 1.0
    assert occupancy.to_dict()["history"] == "keyframes"


class LateSelector:
    """A keyframe set of the previous frame from step 4 on: only episode a (t = 1..6) reaches it."""

    def select(self, actions, box_areas, t):
        return [[t - 1]] if t >= 4 else []


def test_episodes_without_any_memory_are_counted(store):
    episodes, frames = store
    dataset = NavigationStepDataset(
        episodes, frames, "keyframes", capacity=2, set_size=5, keyframe_selector=LateSelector()
    )
    occupancy = memory_occupancy(dataset)
    assert occupancy.episodes_with_memory == 0.5  # a (t = 4, 5, 6), not b
    assert occupancy.without_memory == pytest.approx(6 / 9)
    assert occupancy.steps_to_end_median == pytest.approx(1.0)  # 2, 1, 0


def test_no_memory_and_an_empty_dataset(store):
    episodes, frames = store
    occupancy = memory_occupancy(NavigationStepDataset(episodes, frames, "none", capacity=2, set_size=5))
    assert occupancy.without_memory == 1.0 and occupancy.frames_per_sample == 0.0
    assert occupancy.episodes_with_memory == 0.0 and occupancy.steps_to_end_median is None
    assert occupancy.near_end_fraction == 0.0
    with pytest.raises(ValueError, match="no sample"):
        memory_occupancy(NavigationStepDataset([], frames, "none", capacity=2, set_size=5))
