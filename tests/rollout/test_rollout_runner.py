"""The lockstep runner on the embedded simulator with scripted policies: ends, caps, features and refills by hand."""

from __future__ import annotations

import numpy as np
import pytest
from rollout_scenes import SIZE, free_episodes, tower_env, tower_episode

from openfly_agent import constants as C
from openfly_agent.rollout.policy import OBS_EPISODE_ID, OBS_STEP, OBS_TARGET_BOX, PolicyFeatures
from openfly_agent.rollout.runner import LockstepRunner
from openfly_agent.utils.geometry import Pose


class ScriptedPolicy:
    """Flies each episode's script (by episode id, STOP once it is spent); keeps every observation it is given."""

    name = "scripted"

    def __init__(self, scripts: dict[str, list[int]], features: PolicyFeatures | None = None):
        self.scripts, self.features = scripts, features or PolicyFeatures()
        self.seen: list[dict] = []
        self.calls = self.detail_calls = 0

    def reset(self, episode_ids):
        pass

    def act(self, observations):
        self.calls += 1
        self.seen += observations
        out = []
        for obs in observations:
            script = self.scripts.get(obs[OBS_EPISODE_ID], [])
            out.append(script[obs[OBS_STEP]] if obs[OBS_STEP] < len(script) else C.ACTION_STOP)
        return out

    def step_details(self, episode_ids):
        self.detail_calls += 1
        return [{"box": [0.5, 0.5, 0.1, 0.1], "keyframes": [[0]]} for _ in episode_ids]


def _run(policy, episodes, num_envs, max_steps=C.MAX_EPISODE_STEPS, whole_groups=True):
    records = []
    with tower_env(num_envs) as env:
        runner = LockstepRunner(policy, env, max_steps, whole_groups=whole_groups, show_progress=False)
        stats = runner.run(episodes, "s", records.append)
    return {r.episode_id: r for r in records}, stats


def test_a_policy_that_always_stops_ends_every_episode_after_one_step():
    episodes = free_episodes(5)
    records, stats = _run(ScriptedPolicy({}), episodes, num_envs=2)
    assert set(records) == {e.episode_id for e in episodes}
    for episode in episodes:
        record = records[episode.episode_id]
        start = [*episode.positions[0], episode.yaws[0]]
        assert record.actions == [C.ACTION_STOP] and record.stopped and record.end_reason == "stop"
        assert record.poses == [start, start]
    assert (stats.episodes, stats.steps, stats.policy_calls) == (5, 5, 3)  # groups of 2, 2, 1


def test_the_step_cap_ends_an_episode_that_never_stops():
    (episode,) = free_episodes(1)  # at (-100, -60, 50) facing north: +y
    records, _ = _run(
        ScriptedPolicy({episode.episode_id: [C.ACTION_FORWARD] * 10}), [episode], 1, max_steps=3
    )
    record = records[episode.episode_id]
    assert (
        record.actions == [C.ACTION_FORWARD] * 3 and not record.stopped and record.end_reason == "max_steps"
    )
    np.testing.assert_allclose([p[1] for p in record.poses], [-60.0, -57.0, -54.0, -51.0], atol=1e-9)


def test_a_collision_is_recorded_at_the_step_that_enters_the_tower():
    episode = tower_episode("hit", Pose(60.0, 0.0, 50.0, 0.0), [C.ACTION_STOP])  # facing the face at x = 90
    records, _ = _run(ScriptedPolicy({episode.episode_id: [C.ACTION_FORWARD] * 12}), [episode], 1)
    assert records[episode.episode_id].collision_steps[0] == 9  # the 10th move ends at x = 90


def test_the_target_box_is_given_only_to_a_policy_that_declares_it():
    facing = tower_episode("facing", Pose(0.0, 0.0, 50.0, 0.0), [C.ACTION_STOP])  # the tower dead ahead
    away = tower_episode("away", Pose(0.0, 0.0, 50.0, np.pi), [C.ACTION_STOP])
    boxed = ScriptedPolicy({}, PolicyFeatures(target_box=True))
    _run(boxed, [facing, away], num_envs=2)
    box = {obs[OBS_EPISODE_ID]: obs[OBS_TARGET_BOX] for obs in boxed.seen}
    assert box[away.episode_id] is None
    assert box[facing.episode_id][:2] == pytest.approx([0.5, 0.5], abs=1.0 / SIZE)  # centred
    plain = ScriptedPolicy({})
    _run(plain, [facing], num_envs=1)
    assert plain.seen and all(OBS_TARGET_BOX not in obs for obs in plain.seen)


@pytest.mark.parametrize("declared", [True, False])
def test_step_details_are_read_only_from_a_policy_that_declares_them(declared):
    (episode,) = free_episodes(1)
    policy = ScriptedPolicy({episode.episode_id: [C.ACTION_FORWARD]}, PolicyFeatures(step_details=declared))
    records, _ = _run(policy, [episode], num_envs=1)
    record = records[episode.episode_id]
    assert policy.detail_calls == (2 if declared else 0)
    assert record.boxes == [[0.5, 0.5, 0.1, 0.1] if declared else None] * 2
    assert record.keyframes == [[[0]] if declared else None] * 2


@pytest.mark.parametrize(("whole_groups", "calls"), [(True, 4), (False, 3)])
def test_slots_refill_by_whole_groups_or_as_soon_as_free(whole_groups, calls):
    """a stops at once, b after two moves, c at once; two slots: c waits for b's group, or takes a's slot."""
    a, b, c = free_episodes(3)
    policy = ScriptedPolicy({b.episode_id: [C.ACTION_FORWARD] * 2})
    records, stats = _run(policy, [a, b, c], num_envs=2, whole_groups=whole_groups)
    assert [len(records[e.episode_id].actions) for e in (a, b, c)] == [1, 3, 1]
    assert stats.policy_calls == calls
    first_step_of_c = next(i for i, obs in enumerate(policy.seen) if obs[OBS_EPISODE_ID] == c.episode_id)
    assert first_step_of_c == (4 if whole_groups else 2)  # seen: a, b, b, b, c / a, b, c, b, b (c in slot 0)
