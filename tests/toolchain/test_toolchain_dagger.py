"""DAgger: policy rollouts relabelled with the A* expert's next action from every visited state."""

from __future__ import annotations

import numpy as np
import pytest
from toolchain_scene import BOUNDS, synthetic_scene

from openfly_agent import constants as C
from openfly_agent.sim import dynamics
from openfly_agent.toolchain.actions import build_action_sequence
from openfly_agent.toolchain.astar import ActionSpaceAStar
from openfly_agent.toolchain.config import MapConfig, PlannerConfig
from openfly_agent.toolchain.dagger import (
    NOISE_ACTIONS,
    AStarExpert,
    NoisyExpertPolicy,
    rollout_with_relabel,
)
from openfly_agent.toolchain.pipeline import Rejected
from openfly_agent.toolchain.voxel_map import build_planning_map
from openfly_agent.utils.geometry import Pose

START, GOAL = Pose(-60.0, 0.0, 20.0, 0.3), np.array([60.0, 5.0, 20.0])  # the 60 m tower stands in between


@pytest.fixture(scope="module")
def scene():
    points, _, truth = synthetic_scene()
    pmap = build_planning_map(
        points, MapConfig(voxel_size_m=2.0, dilate_radius_m=3.0, min_height_thresh_m=5.0), BOUNDS, 0.0
    )
    return ActionSpaceAStar(pmap, PlannerConfig()), truth


def _no_frames(pose):
    raise AssertionError("the noisy expert must not ask for frames")


def test_without_noise_the_rollout_is_the_expert_trajectory(scene):
    astar, _ = scene
    poses, labels = rollout_with_relabel(
        AStarExpert(astar, [GOAL]),
        NoisyExpertPolicy(0.0, np.random.default_rng(0)),
        START,
        _no_frames,
        30,
        150,
    )
    seq = build_action_sequence(START, astar.plan(START, GOAL).primitives)
    assert labels == seq.actions.tolist()
    assert np.array_equal(np.array([p.position for p in poses]), seq.positions)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_noisy_rollouts_are_relabelled_with_the_fresh_expert_action(scene, seed):
    astar, truth = scene
    poses, labels = rollout_with_relabel(
        AStarExpert(astar, [GOAL]),
        NoisyExpertPolicy(1.0, np.random.default_rng(seed)),
        START,
        _no_frames,
        6,
        150,
    )
    assert labels[-1] == C.ACTION_STOP and labels.count(C.ACTION_STOP) == 1
    assert np.linalg.norm(poses[-1].position - GOAL) <= astar.cfg.goal_tolerance_m
    for pose, label in zip(poses[:-1], labels[:-1]):
        assert label == AStarExpert(astar, [GOAL]).action(pose)  # a new expert, no cached plan
    moves = [dynamics.apply_action(a, b_label) for a, b_label in zip(poses[:-1], labels[:-1])]
    followed = [m == b for m, b in zip(moves, poses[1:])]
    assert not all(followed[:6])  # the first steps were the policy's random moves, not the labels
    assert all(followed[6:])  # then the expert flies
    for a, b in zip(poses[:-1], poses[1:]):
        assert not truth.segment_collides(a.position, b.position, ground_z=0.0)
        assert any(dynamics.apply_action(a, act) == b for act in NOISE_ACTIONS)  # one executed codebook move


def test_multi_leg_expert_moves_on_after_each_goal(scene):
    astar, _ = scene
    goals = [np.array([-60.0, 60.0, 20.0]), np.array([30.0, 60.0, 20.0])]
    poses, labels = rollout_with_relabel(
        AStarExpert(astar, goals), NoisyExpertPolicy(0.0, np.random.default_rng(0)), START, _no_frames, 0, 150
    )
    assert min(np.linalg.norm(p.position - goals[0]) for p in poses) <= astar.cfg.goal_tolerance_m
    assert np.linalg.norm(poses[-1].position - goals[1]) <= astar.cfg.goal_tolerance_m
    assert labels.count(C.ACTION_STOP) == 1


def test_the_stop_radius_gives_stop_near_the_last_goal_only(scene):
    astar, _ = scene
    goals = [np.array([-60.0, 60.0, 20.0]), GOAL]
    near, far = Pose(*(GOAL + [0.0, 8.0, 0.0]), 0.0), Pose(*(GOAL + [0.0, 12.0, 0.0]), 0.0)
    assert AStarExpert(astar, [GOAL], stop_radius_m=10.0).action(near) == C.ACTION_STOP
    assert AStarExpert(astar, [GOAL], stop_radius_m=10.0).action(far) != C.ACTION_STOP
    assert AStarExpert(astar, [GOAL]).action(near) != C.ACTION_STOP  # A*'s own 3.1-m tolerance
    first_leg = Pose(*(goals[0] + [8.0, 0.0, 0.0]), 0.0)  # within 10 m of the first goal: not reached
    expert = AStarExpert(astar, goals, stop_radius_m=10.0)
    assert expert.action(first_leg) != C.ACTION_STOP and expert.leg == 0
    poses, labels = rollout_with_relabel(
        AStarExpert(astar, [GOAL], stop_radius_m=10.0),
        NoisyExpertPolicy(0.0, np.random.default_rng(0)),
        START,
        _no_frames,
        0,
        150,
    )
    distances = [float(np.linalg.norm(p.position - GOAL)) for p in poses]
    assert labels[-1] == C.ACTION_STOP and distances[-1] <= 10.0 and min(distances[:-1]) > 10.0


def test_rollout_gives_up_after_max_steps(scene):
    astar, _ = scene
    with pytest.raises(Rejected) as err:
        rollout_with_relabel(
            AStarExpert(astar, [GOAL]),
            NoisyExpertPolicy(0.0, np.random.default_rng(0)),
            START,
            _no_frames,
            0,
            3,
        )
    assert err.value.reason == "dagger_max_steps"
