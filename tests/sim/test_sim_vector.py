"""64 embedded episodes in lockstep with a scripted policy: poses, frames, boxes and collisions by hand."""

import math
from dataclasses import dataclass, field

import numpy as np
import pytest

from openfly_agent import constants as C
from openfly_agent.sim.base import EpisodeSpec
from openfly_agent.sim.camera import CameraModel
from openfly_agent.sim.dynamics import rollout_array
from openfly_agent.sim.embedded import EmbeddedSimConfig
from openfly_agent.sim.vector import VectorSimulator
from openfly_agent.utils.geometry import Pose

from .scenes import TOWER_HI, TOWER_LO, assert_same_frame, pixel_box, tower_city, west_face

N_ENVS = 64
SIZE = 96
FREE_ACTIONS = [C.ACTION_FORWARD, C.ACTION_TURN_LEFT, C.ACTION_TURN_RIGHT, C.ACTION_ASCEND, C.ACTION_DESCEND,
                C.ACTION_MOVE_LEFT, C.ACTION_MOVE_RIGHT, C.ACTION_FORWARD_6, C.ACTION_FORWARD_9]  # fmt: skip


def _episodes_and_scripts():
    """Envs 0-15 fly east into the tower; 16-47 fly freely west of it; 48-63 repeat 20-35 with pitch -45."""
    episodes, scripts, expected_hit = [], [], []
    for i in range(16):
        x0 = 60.0 + i % 8  # hits on step ceil((90 - x0) / 3): the first end point inside voxel x >= 90
        start = Pose(x0, -6.0 if i < 8 else 6.0, 50.0, 0.0)
        episodes.append(EpisodeSpec(f"hit-{i}", "test-tower", start))
        scripts.append([C.ACTION_FORWARD] * 10 + [C.ACTION_STOP])
        expected_hit.append(math.ceil((90.0 - x0) / 3.0) - 1)  # 0-based step index
    episodes.append(EpisodeSpec("eye", "test-tower", Pose(0.0, 0.0, 50.0, 0.0)))
    scripts.append([C.ACTION_TURN_LEFT, C.ACTION_TURN_RIGHT, C.ACTION_ASCEND, C.ACTION_STOP])
    expected_hit.append(None)
    for i in range(17, 48):
        rng = np.random.default_rng(i)
        start = Pose(-60.0 - 3 * i, rng.uniform(-100, 100), 60.0, math.pi + rng.uniform(-0.5, 0.5))
        episodes.append(EpisodeSpec(f"free-{i}", "test-tower", start))
        scripts.append(
            [int(a) for a in rng.choice(FREE_ACTIONS, size=int(rng.integers(3, 10)))] + [C.ACTION_STOP]
        )
        expected_hit.append(None)
    for i in range(48, 64):
        twin = i - 28
        base = episodes[twin]
        episodes.append(EpisodeSpec(f"pitched-{i}", "test-tower", base.start, pitch_deg=-45.0))
        scripts.append(scripts[twin])
        expected_hit.append(None)
    # the last two slots run the very same episode: their frames must be identical
    episodes[63], scripts[63] = episodes[62], scripts[62]
    return episodes, scripts, expected_hit


@pytest.fixture(scope="module")
def run():
    episodes, scripts, expected_hit = _episodes_and_scripts()
    vec = VectorSimulator.embedded(EmbeddedSimConfig(width=SIZE, height=SIZE), N_ENVS, cities=[tower_city()])
    frames, flown = {}, [_Flown() for _ in range(N_ENVS)]
    for i, obs in enumerate(vec.reset(episodes)):
        frames[i, 0] = obs
        flown[i].poses.append(obs.pose)
    t = 0
    while any(vec.active):
        actions = [scripts[i][t] if vec.active[i] else None for i in range(N_ENVS)]
        observations, infos = vec.step(actions)
        t += 1
        for i, (obs, info) in enumerate(zip(observations, infos)):
            assert (obs is None) == (actions[i] is None) == (info is None)
            if obs is not None:
                frames[i, t] = obs
                flown[i].poses.append(obs.pose)
                flown[i].actions.append(actions[i])
                flown[i].collided.append(bool(info.collided))
                flown[i].done = bool(info.done)
    yield vec, episodes, scripts, expected_hit, frames, flown
    vec.close()


@dataclass
class _Flown:
    """What one slot flew: poses (start first), actions, per-step collision flags, and whether it ended."""

    poses: list = field(default_factory=list)
    actions: list = field(default_factory=list)
    collided: list = field(default_factory=list)
    done: bool = False

    @property
    def stopped(self) -> bool:
        return bool(self.actions) and self.actions[-1] == C.ACTION_STOP

    @property
    def collision_step(self):
        return self.collided.index(True) if any(self.collided) else None


def test_poses_follow_the_dynamics_until_a_collision(run):
    _, episodes, scripts, expected_hit, _, flown = run
    for i, record in enumerate(flown):
        assert record.collision_step == expected_hit[i], f"env {i}"
        n = len(record.actions)
        reference = rollout_array(episodes[i].start, scripts[i][:n])
        got = np.array([p.as_array() for p in record.poses])
        if expected_hit[i] is None:
            assert record.stopped and record.actions == scripts[i]
            np.testing.assert_allclose(got, reference, atol=1e-9)
        else:
            k = expected_hit[i]
            assert n == k + 1 and not record.stopped  # the collision ended the episode
            np.testing.assert_allclose(got[: k + 1], reference[: k + 1], atol=1e-9)
            np.testing.assert_allclose(got[k + 1], got[k])  # blocked: stays in front of the wall
        assert record.done and record.collided == [j == expected_hit[i] for j in range(n)]


def test_frames_differ_between_poses_and_match_for_equal_episodes(run):
    _, _, _, _, frames, _ = run
    assert not np.array_equal(frames[16, 0].rgb, frames[17, 0].rgb)
    assert not np.array_equal(frames[20, 0].rgb, frames[48, 0].rgb)  # same pose, pitch 0 vs -45
    assert frames[20, 0].pose == frames[48, 0].pose
    for t in range(4):
        if (62, t) in frames:  # the same episode in two batch slots
            assert_same_frame(frames[62, t], frames[63, t])
    for i in range(N_ENVS):
        assert frames[i, 0].rgb.shape == (SIZE, SIZE, 3) and frames[i, 0].rgb.dtype == np.uint8


def test_boxes_match_hand_projection_and_the_renderer(run):
    vec, episodes, _, _, frames, _ = run
    camera = CameraModel(SIZE, SIZE, 90.0)
    tol = 1.0 / SIZE + 1e-9
    start = frames[16, 0]
    face = west_face(TOWER_LO, TOWER_HI)
    np.testing.assert_allclose(start.boxes["b0000"], pixel_box(face, start.pose, camera), atol=tol)
    np.testing.assert_allclose(start.boxes["b0000"][:2], [0.5, 0.5], atol=tol)  # dead ahead: centred
    climbed = frames[16, 3]  # left, right, ascend: 53 m up, yaw back to 0
    assert climbed.pose.z == pytest.approx(53.0) and abs(climbed.pose.yaw) < 1e-12
    np.testing.assert_allclose(climbed.boxes["b0000"], pixel_box(face, climbed.pose, camera), atol=tol)
    sim = vec.sims[0]
    for i, t in [(0, 0), (5, 3), (16, 2), (30, 2), (50, 1), (63, 0)]:
        obs = frames[i, t]
        again = sim.render("test-tower", obs.pose, episodes[i].pitch_deg)
        assert_same_frame(again, obs)


def test_idle_slots_and_bad_calls(run):
    vec = run[0]
    assert not any(vec.active)
    with pytest.raises(ValueError, match="environment 3 has no running episode"):
        vec.step([None] * 3 + [C.ACTION_FORWARD] + [None] * (N_ENVS - 4))
    with pytest.raises(ValueError, match="2 actions for 64 environments"):
        vec.step([None, None])
