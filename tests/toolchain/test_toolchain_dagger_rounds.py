"""DAgger rounds with a policy in the loop: every label is the A* expert's action from the visited state, poses
follow the executed actions, episodes end with the expert's STOP, and a round writes a readable dataset."""

from __future__ import annotations

import dataclasses
import json
import shutil

import numpy as np
import pytest
from test_toolchain_generate import small_config

from openfly_agent import constants as C
from openfly_agent.data.config import ReaderOptions
from openfly_agent.data.frames import FrameStore
from openfly_agent.data.openfly_reader import load_openfly_dataset
from openfly_agent.rollout.policy import PolicyFeatures
from openfly_agent.sim import dynamics
from openfly_agent.sim.city import parse_scene_id
from openfly_agent.toolchain.config import DaggerRoundConfig, GenerateConfig
from openfly_agent.toolchain.dagger import AStarExpert, leg_end_frames
from openfly_agent.toolchain.dagger_rounds import run_dagger_round
from openfly_agent.toolchain.generate import generate
from openfly_agent.toolchain.pipeline import prepare_scene
from openfly_agent.toolchain.render import leg_of_frame
from openfly_agent.toolchain.scenes import embedded_scene
from openfly_agent.toolchain.worker import default_simulator
from openfly_agent.utils.config import load_yaml_config
from openfly_agent.utils.geometry import Pose

TRIM = ReaderOptions(takeoff_landing="trim")


class ScriptedPolicy:
    """Left, forward 9, right, STOP (refused by the round), in turn: a policy that strays off the expert's path."""

    CYCLE = (C.ACTION_TURN_LEFT, C.ACTION_FORWARD_9, C.ACTION_TURN_RIGHT, C.ACTION_STOP, C.ACTION_FORWARD)
    name = "scripted"
    features = PolicyFeatures()

    def __init__(self):
        self.calls, self.resets = 0, []

    def reset(self, episode_ids):
        self.resets += list(episode_ids)

    def act(self, observations):
        out = []
        for obs in observations:
            assert obs[C.OBS_RGB].ndim == 3 and obs[C.OBS_INSTRUCTION]
            out.append(self.CYCLE[obs["step"] % len(self.CYCLE)])
        self.calls += 1
        return out


@pytest.fixture(scope="module")
def dagger_round(tmp_path_factory):
    source = tmp_path_factory.mktemp("nav") / "small"
    generate_cfg = small_config(source)
    # chained routes with each leg's target as the box (the long-route benchmark's labels): the expert must fly
    # the legs in order and each state's box follow its leg
    generate_cfg.route.chain_prob, generate_cfg.render.box_target = 1.0, "leg"
    generate(generate_cfg, progress=False)
    out = tmp_path_factory.mktemp("dagger") / "r1"
    cfg = DaggerRoundConfig(
        source_root=str(source),
        output_dir=str(out),
        episodes=4,
        max_policy_steps=6,
        max_steps=120,
        num_envs=3,
    )
    policy = ScriptedPolicy()
    summary = run_dagger_round(policy, cfg, progress=False)
    return source, out, cfg, policy, summary


def test_labels_are_the_experts_action_from_each_visited_state(dagger_round):
    source, out, cfg, policy, summary = dagger_round
    assert summary["written"] >= 1 and summary["written"] + summary["dropped"] == 4
    generate_cfg = load_yaml_config(GenerateConfig, source / C.TOOLCHAIN_CONFIG_JSON, [])
    episodes = load_openfly_dataset(out, C.SPLIT_TRAIN, TRIM)
    assert len(episodes) == summary["written"] and policy.calls > 0
    planners = {}
    for episode in episodes:
        if episode.scene_id not in planners:
            scene = embedded_scene(parse_scene_id(episode.scene_id), generate_cfg.scenes)
            planners[episode.scene_id] = prepare_scene(scene, generate_cfg).astar
        assert episode.actions[-1] == C.ACTION_STOP and (episode.actions[:-1] != C.ACTION_STOP).all()
        # one expert replayed along the states in order: it plans afresh at each, and moves on to the next leg
        # at the first state within its tolerance of the current leg's goal
        assert len(episode.leg_goals) == len(episode.landmark_ids) >= 2
        expert = AStarExpert(
            planners[episode.scene_id],
            episode.route_goals,
            reuse_plans=False,
            stop_radius_m=cfg.stop_radius_m,
        )
        legs = []
        for t in range(len(episode)):
            pose = Pose(*episode.positions[t], float(episode.yaws[t]))
            assert expert.action(pose) == episode.actions[t], (episode.episode_id, t)
            legs.append(expert.leg)
        assert legs[-1] == len(episode.leg_goals) - 1  # every leg flown, in order
        # the STOP comes on the last leg, at its first state within the stop radius (an earlier leg may pass
        # the final goal closer: the route is flown in order)
        distances = np.linalg.norm(episode.positions - episode.goal, axis=1)
        last_leg = np.asarray(legs) == legs[-1]
        assert (
            distances[-1] <= cfg.stop_radius_m and (distances[:-1][last_leg[:-1]] > cfg.stop_radius_m).all()
        )
        assert min(np.linalg.norm(episode.positions - episode.leg_goals[0], axis=1)) <= expert.tolerance
        for t in range(len(episode) - 1):  # each move is one model action, not necessarily the label
            start = Pose(*episode.positions[t], float(episode.yaws[t]))
            moves = [dynamics.apply_action(start, a) for a in C.MODEL_ACTION_IDS if a != C.ACTION_STOP]
            reached = [
                np.allclose(m.as_array(), np.r_[episode.positions[t + 1], episode.yaws[t + 1]]) for m in moves
            ]
            assert any(reached), (episode.episode_id, t)


def test_rollouts_keep_the_source_instruction_target_and_pitch_and_have_frames(dagger_round):
    source, out, _, _, _ = dagger_round
    sources = {e.episode_id.rsplit("/", 1)[-1]: e for e in load_openfly_dataset(source, C.SPLIT_TRAIN, TRIM)}
    frames = FrameStore(out)
    for episode in load_openfly_dataset(out, C.SPLIT_TRAIN, TRIM):
        origin = sources[episode.episode_id.rsplit("/", 1)[-1].rsplit("_r1_", 1)[0]]
        assert episode.instruction == origin.instruction and episode.landmark_ids == origin.landmark_ids
        assert episode.pitch_deg == origin.pitch_deg and np.allclose(episode.goal, origin.goal)
        np.testing.assert_array_equal(episode.leg_goals, origin.leg_goals)
        np.testing.assert_allclose(episode.positions[0], origin.positions[0])
        assert frames.frame(episode, len(episode) - 1).shape[2] == 3


def test_a_round_resumes_without_running_written_rollouts_again(dagger_round):
    _, _, cfg, _, summary = dagger_round
    again = ScriptedPolicy()
    resumed = run_dagger_round(again, cfg, progress=False)
    assert resumed["written"] == 0 and resumed["rollouts"] == summary["rollouts"]
    if summary["dropped"] == 0:
        assert again.calls == 0  # nothing left to fly


@pytest.mark.parametrize("radius", [-1.0, C.SUCCESS_RADIUS_M])
def test_the_stop_radius_must_lie_inside_the_success_radius(radius):
    with pytest.raises(ValueError, match="stop_radius_m"):
        DaggerRoundConfig(stop_radius_m=radius)


def test_a_leg_box_dataset_without_each_legs_goal_is_refused(dagger_round, tmp_path):
    """Written before `leg_goals` existed, a chained dataset would have its rollouts relabelled straight to the
    final goal, a shortcut no instruction describes: the round refuses it before flying anything."""
    source, _, cfg, _, _ = dagger_round
    old = tmp_path / "old"
    shutil.copytree(source, old)
    for path in (old / "Annotation").rglob("*.json"):
        records = json.loads(path.read_text())
        path.write_text(json.dumps([{k: v for k, v in r.items() if k != "leg_goals"} for r in records]))
    policy = ScriptedPolicy()
    moved = dataclasses.replace(cfg, source_root=str(old), output_dir=str(tmp_path / "r1"))
    with pytest.raises(ValueError, match=r"render.box_target is 'leg' but 4 train episodes .* regenerate"):
        run_dagger_round(policy, moved, progress=False)
    assert policy.calls == 0


def test_generation_time_recovery_episodes_hold_each_states_leg_target(dagger_round):
    """The source dataset's own recovery episodes (generation-time DAgger, `*_dagger`): with `box_target=leg`
    each frame's box is that of the target of the leg the expert was flying at that state."""
    source, _, _, _, _ = dagger_round
    generate_cfg = load_yaml_config(GenerateConfig, source / C.TOOLCHAIN_CONFIG_JSON, [])
    recoveries = [
        e for e in load_openfly_dataset(source, C.SPLIT_TRAIN, TRIM) if e.episode_id.endswith("_dagger")
    ]
    assert recoveries and all(len(e.landmark_ids) >= 2 for e in recoveries)
    sim = default_simulator(generate_cfg)
    astar = {}
    checked = set()
    try:
        for episode in recoveries:
            if episode.scene_id not in astar:
                scene = embedded_scene(parse_scene_id(episode.scene_id), generate_cfg.scenes)
                astar[episode.scene_id] = prepare_scene(scene, generate_cfg).astar
            expert = AStarExpert(astar[episode.scene_id], episode.route_goals)
            legs = []
            for t in range(len(episode)):
                expert.action(Pose(*episode.positions[t], float(episode.yaws[t])))
                legs.append(expert.leg)
            ends = leg_end_frames(legs, len(episode.landmark_ids))
            for t in range(0, len(episode), 2):
                target = episode.landmark_ids[leg_of_frame(ends, t)]
                obs = sim.render(
                    episode.scene_id, Pose(*episode.positions[t], episode.yaws[t]), episode.pitch_deg
                )
                assert bool(episode.box_visible[t]) == (target in (obs.boxes or {})), (episode.episode_id, t)
                if episode.box_visible[t]:
                    assert np.allclose(episode.boxes[t], obs.boxes[target], atol=1e-6)
                    checked.add(leg_of_frame(ends, t))
    finally:
        sim.close()
    assert len(checked) >= 2  # visible boxes of more than one leg were compared
