"""Generation-time DAgger: policy rollouts through the lockstep runner, relabelled with the A* expert's next action
from every visited state."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from toolchain_scene import BOUNDS, synthetic_scene

from openfly_agent import constants as C
from openfly_agent.data.schema import Episode
from openfly_agent.rollout.policy import OBS_EXPERT_ACTION, OBS_STEP, PolicyFeatures
from openfly_agent.rollout.runner import LockstepRunner, RolloutHook
from openfly_agent.sim import dynamics
from openfly_agent.sim.base import Observation
from openfly_agent.sim.free_flight import FreeFlightSimulator
from openfly_agent.sim.vector import VectorSimulator
from openfly_agent.toolchain.actions import build_action_sequence
from openfly_agent.toolchain.astar import ActionSpaceAStar
from openfly_agent.toolchain.config import MapConfig, PlannerConfig
from openfly_agent.toolchain.dagger import NoisyExpertPolicy, leg_end_frames, relabelled_rollout
from openfly_agent.toolchain.expert import POLICY_MOVES, AStarExpert, ExpertLabelling
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


def _no_frames(scene_id, pose, pitch_deg):
    raise AssertionError("the noisy expert must not ask for frames")


def _route(start: Pose, goal: np.ndarray, pitch_deg: float = 0.0) -> Episode:
    """A route as the runner's episode: the start pose, the final goal, the scene and the camera pitch."""
    return Episode(
        episode_id="synthetic/dagger/0",
        scene_id="synthetic",
        instruction="",
        actions=[C.ACTION_STOP],
        positions=[start.position],
        yaws=[start.yaw],
        frame_ids=["0"],
        pitch_deg=pitch_deg,
        goal=goal,
    )


def _fly(expert, policy, start, render, max_policy_steps, max_steps, hooks=()):
    """(visited poses, labels) of one relabelled rollout from `start` to the expert's last goal."""
    rollout = relabelled_rollout(
        policy, _route(start, expert.goals[-1]), expert, max_policy_steps, max_steps, render, hooks
    )
    return rollout.poses, rollout.labels


def test_without_noise_the_rollout_is_the_expert_trajectory(scene):
    astar, _ = scene
    poses, labels = _fly(
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
    poses, labels = _fly(
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
        assert any(dynamics.apply_action(a, act) == b for act in POLICY_MOVES)  # one executed codebook move


def test_multi_leg_expert_moves_on_after_each_goal(scene):
    astar, _ = scene
    goals = [np.array([-60.0, 60.0, 20.0]), np.array([30.0, 60.0, 20.0])]
    poses, labels = _fly(
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
    poses, labels = _fly(
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
        _fly(
            AStarExpert(astar, [GOAL]),
            NoisyExpertPolicy(0.0, np.random.default_rng(0)),
            START,
            _no_frames,
            0,
            3,
        )
    assert err.value.reason == "dagger_max_steps"


class Scripted:
    """Proposes `script[step]` (STOP once spent); with `frames`, keeps the rgb and pose of every observation."""

    name = "scripted"

    def __init__(self, script: list[int], frames: bool = False):
        self.script, self.features = script, PolicyFeatures(frames=frames)
        self.seen: list[dict] = []

    def reset(self, episode_ids):
        pass

    def act(self, observations):
        self.seen += observations
        return [
            self.script[o[OBS_STEP]] if o[OBS_STEP] < len(self.script) else C.ACTION_STOP
            for o in observations
        ]


class StepLog(RolloutHook):
    """What the runner shows its hooks: every step's pose and executed action, and the episode's end."""

    def __init__(self):
        self.steps, self.ends = [], []

    def on_step(self, running, action):
        self.steps.append((running.obs.pose, action))

    def on_episode_end(self, running):
        self.ends.append(running.record)


def test_the_rollout_goes_through_the_lockstep_runner(scene):
    astar, _ = scene
    log = StepLog()
    poses, labels = _fly(
        AStarExpert(astar, [GOAL]),
        NoisyExpertPolicy(0.5, np.random.default_rng(3)),
        START,
        _no_frames,
        8,
        150,
        [log],
    )
    assert [pose for pose, _ in log.steps] == poses[:-1]  # every visited state but the last, the STOP
    assert [dynamics.apply_action(p, a) for p, a in log.steps] == poses[1:]
    (record,) = log.ends
    assert record.actions == [a for _, a in log.steps] and record.poses[-1] == list(poses[-1].as_array())
    assert labels[-1] == C.ACTION_STOP and len(labels) == len(log.steps) + 1


def test_hand_checked_labels_on_a_short_straight_route(scene):
    """18 m east in free air: A* flies 15 m (9 + 6) into its 3.1-m tolerance. The policy's lateral move is
    replaced by the label, its left turn is flown, then the expert turns back and finishes."""
    astar, _ = scene
    start, goal = Pose(-60.0, 0.0, 20.0, 0.0), np.array([-42.0, 0.0, 20.0])
    policy = Scripted([C.ACTION_MOVE_LEFT, C.ACTION_TURN_LEFT], frames=True)
    rendered = []

    def render(scene_id, pose, pitch_deg):
        rendered.append((scene_id, pose, pitch_deg))
        return Observation(rgb=np.full((2, 2, 3), len(rendered), np.uint8), pose=pose)

    rollout = relabelled_rollout(
        policy, _route(start, goal, -45.0), AStarExpert(astar, [goal]), 2, 150, render
    )
    F9, F6, TR, S = C.ACTION_FORWARD_9, C.ACTION_FORWARD_6, C.ACTION_TURN_RIGHT, C.ACTION_STOP
    assert rollout.labels == [F9, F6, TR, F6, S]
    turned = Pose(-51.0, 0.0, 20.0, np.deg2rad(30.0))
    assert rollout.poses[:2] == [start, Pose(-51.0, 0.0, 20.0, 0.0)]  # MOVE_LEFT refused: forward 9 flown
    assert rollout.poses[2].position.tolist() == [-51.0, 0.0, 20.0]
    assert rollout.poses[2].yaw == pytest.approx(turned.yaw)  # the policy's left turn was flown
    assert rollout.poses[3].yaw == pytest.approx(0.0) and rollout.poses[4].position.tolist() == [
        -45.0,
        0.0,
        20.0,
    ]
    assert [o[C.OBS_RGB][0, 0, 0] for o in policy.seen] == [1, 2]  # the frames of the poses it acted at
    assert [o[C.OBS_POSE].tolist() for o in policy.seen] == [p.as_array().tolist() for p in rollout.poses[:2]]
    assert len(rendered) == 2  # the states the policy may act at, no more
    assert all(call[0] == "synthetic" and call[2] == -45.0 for call in rendered)


def test_a_policy_move_across_the_dilated_map_is_replaced_by_the_label(scene):
    astar, truth = scene
    start, goal = Pose(-30.0, 0.0, 20.0, 0.0), np.array([-30.0, -30.0, 20.0])  # the tower's face is 10 m east
    assert astar.segment_blocked(start.position, dynamics.apply_action(start, C.ACTION_FORWARD_9).position)
    expert = AStarExpert(astar, [goal])
    poses, labels = _fly(expert, Scripted([C.ACTION_FORWARD_9]), start, _no_frames, 1, 150)
    assert labels[0] == AStarExpert(astar, [goal]).action(start) != C.ACTION_FORWARD_9
    assert poses[1] == dynamics.apply_action(start, labels[0])  # the label was flown, not forward 9
    assert labels[-1] == C.ACTION_STOP


def test_a_policy_that_reads_frames_needs_a_render_function(scene):
    astar, _ = scene
    with pytest.raises(ValueError, match="render"):
        _fly(AStarExpert(astar, [GOAL]), Scripted([], frames=True), START, None, 1, 150)


def test_the_expert_without_a_plan_rejects_the_rollout(scene):
    astar, _ = scene
    inside = np.array([0.0, 0.0, 20.0])  # in the tower: no plan from anywhere
    with pytest.raises(Rejected) as err:
        _fly(
            AStarExpert(astar, [inside]),
            NoisyExpertPolicy(0.0, np.random.default_rng(0)),
            START,
            _no_frames,
            0,
            150,
        )
    assert err.value.reason == "dagger_expert_failed"


def test_leg_end_frames_follow_the_a_star_episodes_convention():
    """A leg ends at the first state of the next leg (that state is the next leg's first decision); the last
    leg at the last state, the STOP (`leg_of_frame` reads them back)."""
    assert leg_end_frames([0, 0, 1, 1, 1], 2) == [2, 4]
    assert leg_end_frames([0, 1, 2], 3) == [1, 2, 2]
    assert leg_end_frames([0, 0, 0], 1) == [2]
    assert leg_end_frames([0, 2, 2], 3) == [1, 1, 2]  # a state that reaches two leg goals at once
    with pytest.raises(ValueError, match="never left leg 1 of 3"):
        leg_end_frames([0, 1, 1], 3)


class FollowTheLabel:
    """Flies the expert's label (given in its observation) and reads frames, so every state is rendered."""

    name = "follow_the_label"
    features = PolicyFeatures(frames=True, expert_action=True)

    def reset(self, episode_ids):
        pass

    def act(self, observations):
        return [int(o[OBS_EXPERT_ACTION]) for o in observations]


def _labelled(astar, episode, box_target, boxes):
    """The `DaggerRollout` of `episode` flown by `FollowTheLabel` under `ExpertLabelling(box_target)`, in a
    world that shows every landmark of `boxes` at its fixed box in every frame."""

    def render(scene_id, pose, pitch_deg):
        return Observation(rgb=np.zeros((2, 2, 3), np.uint8), pose=pose, boxes=dict(boxes))

    ended = []
    labelling = ExpertLabelling(
        lambda e: AStarExpert(astar, e.route_goals),
        ended.append,
        max_policy_steps=150,
        max_steps=150,
        label_in_observation=True,
        box_target=box_target,
    )
    with VectorSimulator(sims=[FreeFlightSimulator(render, render_steps=150)]) as env:
        runner = LockstepRunner(
            FollowTheLabel(), env, 151, [labelling], whole_groups=False, show_progress=False
        )
        runner.run([episode], C.SPLIT_TRAIN)
    (rollout,) = ended
    return rollout


def test_each_state_records_the_experts_leg_and_that_legs_target_box(scene):
    """Two legs: the expert moves to leg 1 at the first state within its tolerance of leg 0's goal; with
    `box_target=leg` each state's box is its leg's target's (`final`: the last target's throughout), and the
    legs give the end frames the A* episodes use."""
    astar, _ = scene
    goals = [np.array([-60.0, 60.0, 20.0]), np.array([30.0, 60.0, 20.0])]
    boxes = {"first": (0.2, 0.5, 0.1, 0.1), "second": (0.7, 0.5, 0.2, 0.2), "other": (0.5, 0.5, 0.3, 0.3)}
    episode = dataclasses.replace(
        _route(START, goals[-1]), landmark_ids=["first", "second"], leg_goals=np.array(goals)
    )
    rollout = _labelled(astar, episode, "leg", boxes)
    n, k = len(rollout.poses), rollout.legs.index(1)
    assert rollout.failed is None and rollout.labels[-1] == C.ACTION_STOP and 0 < k < n - 1
    assert rollout.legs == [0] * k + [1] * (n - k)
    tolerance = astar.cfg.goal_tolerance_m
    assert np.linalg.norm(rollout.poses[k].position - goals[0]) <= tolerance
    assert all(np.linalg.norm(p.position - goals[0]) > tolerance for p in rollout.poses[:k])
    np.testing.assert_array_equal(rollout.boxes, [boxes["first"]] * k + [boxes["second"]] * (n - k))
    assert leg_end_frames(rollout.legs, 2) == [k, n - 1]
    final = _labelled(astar, episode, "final", boxes)
    assert final.labels == rollout.labels
    np.testing.assert_array_equal(final.boxes, [boxes["second"]] * n)


def test_leg_boxes_need_one_expert_goal_per_target(scene):
    astar, _ = scene
    episode = dataclasses.replace(_route(START, GOAL), landmark_ids=["first", "second"])  # no leg goals
    with pytest.raises(ValueError, match="needs one expert goal per target landmark, got 1 goals for 2"):
        _labelled(astar, episode, "leg", {})
    with pytest.raises(ValueError, match="box_target must be one of"):
        ExpertLabelling(lambda e: None, print, max_policy_steps=1, max_steps=1, box_target="next")
