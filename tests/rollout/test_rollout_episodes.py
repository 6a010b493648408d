"""A dataset episode as a simulator task: its start spec by hand, and its actions replayed through the runner
land on its recorded positions (Episode -> EpisodeSpec -> simulator -> record)."""

from __future__ import annotations

import dataclasses

import numpy as np
from rollout_scenes import TOWER, tower_env, tower_episode
from test_rollout_runner import ScriptedPolicy

from openfly_agent import constants as C
from openfly_agent.rollout.episodes import episode_spec, goal_of, reference_path, target_landmark
from openfly_agent.rollout.runner import LockstepRunner
from openfly_agent.utils.geometry import Pose

ROUTE = [C.ACTION_FORWARD, C.ACTION_TURN_LEFT, C.ACTION_FORWARD_9, C.ACTION_ASCEND, C.ACTION_STOP]


def test_the_spec_starts_at_the_first_pose_with_the_goal_and_the_target():
    episode = tower_episode("spec", Pose(-20.0, 5.0, 40.0, 0.25), ROUTE)
    spec = episode_spec(episode)
    assert spec.episode_id == episode.episode_id and spec.scene_id == "test-tower"
    assert spec.start == Pose(-20.0, 5.0, 40.0, 0.25) and spec.pitch_deg == 0.0
    np.testing.assert_array_equal(spec.goal, episode.positions[-1])  # no goal given: the last position
    assert spec.landmark_id == TOWER == target_landmark(episode)
    aimed = dataclasses.replace(episode, goal=np.array([1.0, 2.0, 3.0]), landmark_ids=[])
    np.testing.assert_array_equal(goal_of(aimed), [1.0, 2.0, 3.0])
    assert episode_spec(aimed).landmark_id is None


def test_replaying_the_actions_from_the_spec_lands_on_the_recorded_positions():
    episode = tower_episode("replay", Pose(-20.0, 5.0, 40.0, 0.25), ROUTE)
    records = []
    with tower_env(1) as env:
        policy = ScriptedPolicy({episode.episode_id: ROUTE})
        LockstepRunner(policy, env, show_progress=False).run([episode], "s", records.append)
    (record,) = records
    assert record.actions == ROUTE and record.stopped
    visited = np.array(record.poses)  # (T + 1, 4): the STOP repeats the last pose
    np.testing.assert_allclose(visited[:-1, :3], episode.positions, atol=1e-9)
    np.testing.assert_allclose(visited[:-1, 3], episode.yaws, atol=1e-9)
    assert record.reference_path == reference_path(episode).tolist()
    assert record.goal == episode.positions[-1].tolist()
