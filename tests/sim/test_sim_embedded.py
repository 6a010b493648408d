"""EmbeddedSimulator: generated scenes by id, observations, config checks, lifetime and fork safety."""

import math

import numpy as np
import pytest

from openfly_agent import constants as C
from openfly_agent.sim import renderer as R
from openfly_agent.sim.base import EpisodeSpec, Simulator
from openfly_agent.sim.city import CityConfig
from openfly_agent.sim.embedded import EmbeddedSimConfig, EmbeddedSimulator
from openfly_agent.utils.geometry import Pose

TINY = CityConfig(size_m=300.0, n_buildings=30, n_trees=40)


@pytest.fixture(scope="module")
def sim():
    s = EmbeddedSimulator(EmbeddedSimConfig(width=64, height=48, city=TINY, render_depth=True))
    yield s
    s.close()


def test_generated_scene_by_id(sim):
    assert isinstance(sim, Simulator)
    episode = EpisodeSpec("e1", "embedded-5", Pose(-170.0, -170.0, 70.0, math.pi / 4), pitch_deg=-45.0)
    obs = sim.reset(episode)
    assert obs.rgb.shape == (48, 64, 3) and obs.depth.shape == (48, 64) and obs.depth.dtype == np.float32
    city = sim.city("embedded-5")
    assert city.seed == 5 and len(city.buildings) == 30
    ids = {lm.landmark_id for lm in city.landmarks}
    assert obs.boxes and set(obs.boxes) <= ids and set(obs.extra["pixel_counts"]) == set(obs.boxes)
    assert all(n >= 16 for n in obs.extra["pixel_counts"].values())
    for box in obs.boxes.values():
        assert np.all(box > 0) and np.all(box <= 1)
    obs2, info = sim.step(C.ACTION_TURN_LEFT)
    assert obs2.pose.yaw == pytest.approx(math.pi / 4 + math.pi / 6) and not info.done
    obs3, info = sim.step(C.ACTION_STOP)
    assert info.done and obs3 is obs2  # STOP does not move, so the frame is reused
    assert len(sim.poses) == 3 and sim.collided == [False, False]


def test_render_does_not_touch_the_episode(sim):
    sim.reset(EpisodeSpec("e2", "embedded-5", Pose(0.0, 0.0, 80.0, 0.0)))
    before = sim.poses
    obs = sim.render("embedded-6", Pose(10.0, 10.0, 90.0, 1.0), pitch_deg=-45.0)
    assert obs.extra["scene_id"] == "embedded-6" and obs.extra["pitch_deg"] == -45.0
    assert sim.poses == before and sim.pose == Pose(0.0, 0.0, 80.0, 0.0)


def test_errors_say_what_is_wrong():
    with pytest.raises(ValueError, match="collision policy must be one of"):
        EmbeddedSimConfig(collision="bounce")
    with pytest.raises(ValueError, match="width/height"):
        EmbeddedSimConfig(width=4)
    s = EmbeddedSimulator(EmbeddedSimConfig(width=16, height=16, city=TINY))
    with pytest.raises(RuntimeError, match="call reset"):
        s.step(C.ACTION_FORWARD)
    with pytest.raises(ValueError, match="embedded-<non-negative integer>"):
        s.reset(EpisodeSpec("e", "env_airsim_16", Pose(0, 0, 10, 0)))
    s.close()
    s.close()
    with pytest.raises(RuntimeError, match="closed"):
        s.reset(EpisodeSpec("e", "embedded-1", Pose(0, 0, 10, 0)))


def test_siblings_share_one_context_until_the_last_closes():
    first = EmbeddedSimulator(EmbeddedSimConfig(width=16, height=16, city=TINY))
    second = first.sibling()
    assert second.renderer is first.renderer
    second.render("embedded-1", Pose(0, 0, 50, 0))
    first.close()
    assert first.renderer._ctx is not None  # the sibling still renders
    second.render("embedded-1", Pose(0, 0, 50, 1))
    second.close()
    assert first.renderer._ctx is None


def test_a_context_from_another_process_is_refused(monkeypatch):
    s = EmbeddedSimulator(EmbeddedSimConfig(width=16, height=16, city=TINY))
    s.render("embedded-1", Pose(0, 0, 50, 0))
    monkeypatch.setattr(R.os, "getpid", lambda: -1)  # as in a forked child
    with pytest.raises(RuntimeError, match="cannot be used after fork"):
        s.render("embedded-1", Pose(0, 0, 50, 0))
    monkeypatch.undo()
    s.close()


def test_a_city_in_use_is_not_rebuilt_after_eviction():
    s = EmbeddedSimulator(EmbeddedSimConfig(width=16, height=16, city=TINY, max_cached_scenes=1))
    s.reset(EpisodeSpec("e", "embedded-1", Pose(0, 0, 60, 0)))
    held = s.city("embedded-1")
    s.render("embedded-2", Pose(0, 0, 60, 0))  # evicts embedded-1 from the cache of one
    assert s.city("embedded-1") is held  # the running episode's city comes back, not a rebuilt copy
    s.close()
