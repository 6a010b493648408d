"""DAgger rounds with a policy in the loop: every label is the A* expert's action from the visited state, poses
follow the executed actions, episodes end with the expert's STOP, and a round writes a readable dataset."""

from __future__ import annotations

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
from openfly_agent.toolchain.dagger import AStarExpert
from openfly_agent.toolchain.dagger_rounds import run_dagger_round
from openfly_agent.toolchain.generate import generate
from openfly_agent.toolchain.pipeline import prepare_scene
from openfly_agent.toolchain.scenes import embedded_scene
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
    generate(small_config(source), progress=False)
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
        distances = np.linalg.norm(episode.positions - episode.goal, axis=1)
        assert distances[-1] <= cfg.stop_radius_m and (distances[:-1] > cfg.stop_radius_m).all()
        for t in range(len(episode)):
            pose = Pose(*episode.positions[t], float(episode.yaws[t]))
            expert = AStarExpert(
                planners[episode.scene_id], [episode.goal], reuse_plans=False, stop_radius_m=cfg.stop_radius_m
            )
            assert expert.action(pose) == episode.actions[t], (episode.episode_id, t)
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
