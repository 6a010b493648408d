"""Runner hooks: they see every start, step and end in order, and may end an episode, keep the policy out of a
step and replace its action."""

from __future__ import annotations

import math

import pytest
from rollout_scenes import free_episodes, tower_env
from test_rollout_runner import ScriptedPolicy

from openfly_agent import constants as C
from openfly_agent.rollout.runner import LockstepRunner, RolloutHook


class EventLog(RolloutHook):
    def __init__(self):
        self.events = []

    def on_episode_start(self, running):
        self.events.append(("start", running.episode.episode_id[-1]))

    def on_step(self, running, action):
        y = running.obs.pose.y  # the state the action is taken from
        self.events.append(("step", running.episode.episode_id[-1], len(running.record.actions), action, y))

    def on_episode_end(self, running):
        self.events.append(("end", running.episode.episode_id[-1], list(running.record.actions)))


def test_a_hook_sees_every_step_in_order():
    a, b = free_episodes(2)  # ids end in 0 and 1; both start at y = -60 / -40, facing +y
    policy = ScriptedPolicy(
        {a.episode_id: [C.ACTION_FORWARD], b.episode_id: [C.ACTION_TURN_LEFT, C.ACTION_FORWARD]}
    )
    log = EventLog()
    with tower_env(2) as env:
        LockstepRunner(policy, env, hooks=[log], show_progress=False).run([a, b], "s")
    F, L, S = C.ACTION_FORWARD, C.ACTION_TURN_LEFT, C.ACTION_STOP
    assert [e[:4] for e in log.events] == [
        ("start", "0"), ("start", "1"),
        ("step", "0", 0, F), ("step", "1", 0, L),
        ("step", "0", 1, S), ("step", "1", 1, F),
        ("end", "0", [F, S]),
        ("step", "1", 2, S),
        ("end", "1", [L, F, S]),
    ]  # fmt: skip
    ys = {(e[1], e[2]): e[4] for e in log.events if e[0] == "step"}
    assert ys[("0", 0)] == -60.0 and ys[("0", 1)] == -57.0  # forward 3 m along +y
    assert ys[("1", 1)] == -40.0  # a turn does not move
    assert ys[("1", 2)] == pytest.approx(-40.0 + 3.0 * math.cos(math.radians(30.0)))  # 3 m, 30 degrees off +y


class ExpertTakesOver(RolloutHook):
    """The policy chooses the first action only; then forward 6 m; the episode ends before its 4th action."""

    def asks_policy(self, running):
        return not running.record.actions

    def choose_action(self, running, proposed):
        return C.ACTION_FORWARD_6 if proposed is None else proposed

    def before_act(self, running):
        return len(running.record.actions) == 3


def test_a_hook_ends_episodes_keeps_the_policy_out_and_replaces_its_action():
    episodes = free_episodes(3)
    policy = ScriptedPolicy({e.episode_id: [C.ACTION_TURN_RIGHT] * 10 for e in episodes})
    records = []
    with tower_env(2) as env:
        runner = LockstepRunner(policy, env, hooks=[ExpertTakesOver()], show_progress=False)
        stats = runner.run(episodes, "s", records.append)
    assert [r.actions for r in records] == [[C.ACTION_TURN_RIGHT, C.ACTION_FORWARD_6, C.ACTION_FORWARD_6]] * 3
    assert policy.calls == 2 and len(policy.seen) == 3  # one call per group, at its first step
    assert stats.steps == 9
    assert all(not r.stopped and r.boxes == [None] * 3 for r in records)


class TellsTheStep(RolloutHook):
    """Adds the number of actions taken so far, twice over, to every observation the policy gets."""

    def observation_fields(self, running):
        return {"hint": 2 * len(running.record.actions)}


def test_a_hook_adds_fields_to_the_policy_observation():
    (episode,) = free_episodes(1)
    policy = ScriptedPolicy({episode.episode_id: [C.ACTION_FORWARD, C.ACTION_TURN_LEFT]})
    with tower_env(1) as env:
        LockstepRunner(policy, env, hooks=[TellsTheStep()], show_progress=False).run([episode], "s")
    assert [(obs["step"], obs["hint"]) for obs in policy.seen] == [(0, 0), (1, 2), (2, 4)]
