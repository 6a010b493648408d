"""What the RL stage makes of a flight (training/rl_rollouts.py): its reward under a metric profile (20 m
radius, worked out by hand), the group's episode ids, and a recorded step as a training sample."""

from __future__ import annotations

import numpy as np
import pytest

from openfly_agent import constants as C
from openfly_agent.data.schema import Episode
from openfly_agent.rollout.profiles import STANDARD
from openfly_agent.rollout.record import EpisodeRecord
from openfly_agent.training.config import RLConfig
from openfly_agent.training.rl_rollouts import RolloutStep, group_episodes, rollout_reward, step_sample

GOAL = [100.0, 0.0, 10.0]


def flight(end_x: float, stopped: bool = True, collision_steps=()) -> EpisodeRecord:
    """From (0, 0, 10) east to (end_x, 0, 10) in moves of 10 m, then STOP when `stopped`."""
    xs = list(np.arange(0.0, end_x + 1e-9, 10.0))
    poses = [[x, 0.0, 10.0, 0.0] for x in xs]
    actions = [1] * (len(xs) - 1)
    if stopped:
        actions.append(C.ACTION_STOP)
        poses.append(poses[-1])
    return EpisodeRecord(
        split="train", episode_id="e#rl0", scene_id="embedded-0", policy="rl", instruction="fly east",
        goal=GOAL, reference_path=[[0.0, 0.0, 10.0], GOAL], actions=actions, poses=poses, stopped=stopped,
        end_reason="stop" if stopped else "max_steps", collision_steps=list(collision_steps),
    )  # fmt: skip


def test_success_alone_by_default():
    rl = RLConfig()
    assert rollout_reward(flight(90.0), STANDARD, rl) == (1.0, True)  # 10 m from the goal, STOP: success
    assert rollout_reward(flight(50.0), STANDARD, rl) == (0.0, False)  # 50 m short
    assert rollout_reward(flight(90.0, stopped=False), STANDARD, rl) == (
        0.0,
        False,
    )  # no STOP: standard fails


def test_shaping_terms_when_switched_on():
    rl = RLConfig(progress_weight=0.5, collision_penalty=0.25, far_stop_penalty=0.1)
    # 100 m at the start, 50 m at the end: progress 0.5 x 50 / 100 = 0.25; a STOP 50 m away: -0.1
    reward, success = rollout_reward(flight(50.0), STANDARD, rl)
    assert not success and reward == pytest.approx(0.25 - 0.1)
    # the standard profile ends a flight at its collision (step 2, at x = 20): progress 0.5 x 20 / 100 = 0.1,
    # then -0.25; no STOP was flown (the collision came first), so no far-STOP term
    reward, _ = rollout_reward(flight(50.0, collision_steps=[2]), STANDARD, rl)
    assert reward == pytest.approx(0.1 - 0.25)
    # success: 1 + 0.5 x 90 / 100
    assert rollout_reward(flight(90.0), STANDARD, rl)[0] == pytest.approx(1.45)
    # flown on to the step limit 10 m from the goal: progress 0.5 x 90 / 100, above the STOP 50 m short (0.15)
    assert rollout_reward(flight(90.0, stopped=False), STANDARD, rl) == (pytest.approx(0.45), False)


def test_group_episodes_repeat_each_source_with_its_own_id():
    source = Episode(
        episode_id="s/1", scene_id="embedded-0", instruction="go", actions=np.zeros(1, np.int64),
        positions=np.zeros((1, 3)), yaws=np.zeros(1), frame_ids=["f0"],
    )  # fmt: skip
    episodes = group_episodes([source], 3)
    assert [e.episode_id for e in episodes] == ["s/1#rl0", "s/1#rl1", "s/1#rl2"]
    assert all(e.instruction == "go" and e.scene_id == "embedded-0" for e in episodes)


def test_a_step_sample_replays_what_the_policy_saw():
    frames = [np.full((8, 8, 3), i, np.uint8) for i in range(4)]
    steps = [
        RolloutStep(frames[0], 1, [0.5, 0.5, 0.2, 0.2], None, True, []),
        RolloutStep(frames[1], 2, None, [0.4, 0.4, 0.1, 0.1], True, []),
        RolloutStep(frames[2], 1, [0.3, 0.3, 0.1, 0.1], [0.3, 0.4, 0.1, 0.2], True, [[0, 1]]),
    ]
    sample = step_sample(flight(20.0, stopped=False), steps, 2)
    assert sample[C.ACTION] == 1 and sample[C.STEP_INDEX] == 2 and sample[C.OBS_INSTRUCTION] == "fly east"
    assert sample[C.OBS_RGB] is frames[2]
    # the grounding target is the simulator's box; the box token gets the policy's own prediction
    assert sample[C.BOX].tolist() == pytest.approx([0.3, 0.4, 0.1, 0.2]) and sample[C.BOX_VISIBLE]
    assert sample[C.TOKEN_BOX].tolist() == pytest.approx([0.3, 0.3, 0.1, 0.1]) and sample[C.TOKEN_BOX_VISIBLE]
    # memory: one set of frames 0 and 1 with the boxes the policy predicted there (none at frame 1)
    ((first, second),) = sample[C.MEMORY]
    assert first[0] is frames[0] and first[1].tolist() == pytest.approx([0.5, 0.5, 0.2, 0.2]) and first[2]
    assert second[0] is frames[1] and not second[2] and second[1].tolist() == [0.0] * 4
    assert not step_sample(flight(20.0, stopped=False), steps, 0)[C.BOX_VISIBLE]
