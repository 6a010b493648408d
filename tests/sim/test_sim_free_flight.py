"""FreeFlightSimulator: poses by sim/dynamics.py, never a collision, frames only through its render callback."""

import math

import numpy as np
import pytest

from openfly_agent import constants as C
from openfly_agent.sim.base import EpisodeSpec, Observation
from openfly_agent.sim.free_flight import FreeFlightSimulator
from openfly_agent.sim.vector import VectorSimulator
from openfly_agent.utils.geometry import Pose

SPEC = EpisodeSpec("e0", "embedded-3", Pose(10.0, 20.0, 30.0, 0.0), pitch_deg=-45.0)


def test_without_render_it_flies_the_dynamics_with_black_frames():
    sim = FreeFlightSimulator()
    obs = sim.reset(SPEC)
    assert obs.pose == SPEC.start and obs.rgb.shape == (1, 1, 3) and not obs.rgb.any() and obs.boxes == {}
    obs, info = sim.step(C.ACTION_FORWARD_9)
    assert obs.pose == Pose(19.0, 20.0, 30.0, 0.0) and not info.collided and not info.done
    obs, _ = sim.step(C.ACTION_TURN_LEFT)
    obs, _ = sim.step(C.ACTION_MOVE_RIGHT)  # 3 m right of a heading 30 degrees left of +x
    assert obs.pose.x == pytest.approx(19.0 + 3.0 * math.sin(math.radians(30.0)))
    assert obs.pose.y == pytest.approx(20.0 - 3.0 * math.cos(math.radians(30.0)))
    obs, info = sim.step(C.ACTION_STOP)
    assert info.done and obs.pose.y == pytest.approx(20.0 - 3.0 * math.cos(math.radians(30.0)))
    with pytest.raises(RuntimeError, match="reset"):
        sim.step(C.ACTION_FORWARD)


def test_render_is_called_once_per_visited_pose_with_the_scene_and_pitch():
    calls = []

    def render(scene_id, pose, pitch_deg):
        calls.append((scene_id, pose, pitch_deg))
        return Observation(rgb=np.full((4, 4, 3), len(calls), np.uint8), pose=Pose(0.0, 0.0, 0.0, 0.0))

    with VectorSimulator(sims=[FreeFlightSimulator(render)]) as env:
        first = env.reset_env(0, SPEC)
        (second,), _ = env.step([C.ACTION_ASCEND])
    assert calls == [("embedded-3", SPEC.start, -45.0), ("embedded-3", Pose(10.0, 20.0, 33.0, 0.0), -45.0)]
    assert first.rgb[0, 0, 0] == 1 and second.rgb[0, 0, 0] == 2
    # each observation carries the simulator's own pose, not the one render put in it
    assert first.pose == SPEC.start and second.pose == Pose(10.0, 20.0, 33.0, 0.0)


def test_render_steps_limits_rendering_to_the_first_poses_of_each_episode():
    calls = []

    def render(scene_id, pose, pitch_deg):
        calls.append(pose)
        return Observation(rgb=np.full((4, 4, 3), 9, np.uint8), pose=pose)

    sim = FreeFlightSimulator(render, render_steps=2)
    frames = [sim.reset(SPEC).rgb] + [sim.step(C.ACTION_FORWARD)[0].rgb for _ in range(3)]
    assert [f.shape for f in frames] == [(4, 4, 3)] * 2 + [(1, 1, 3)] * 2 and len(calls) == 2
    sim.reset(SPEC)  # a new episode renders again
    assert len(calls) == 3 and calls[-1] == SPEC.start
