"""Small builders shared by the evaluation tests: episodes that replay exactly, and a pose-only simulator.

`PoseSimulator` is a test double for the injected simulator: motion through `sim/dynamics.py`, collisions
against an `OccupancyGrid`, and a 4 x 4 frame whose pixels encode the pose (so a policy that looks at
frames sees different frames at different poses). The end-to-end tests use the embedded simulator.
"""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import numpy as np

from openfly_agent import constants as C
from openfly_agent.data.schema import Episode
from openfly_agent.eval.config import EvalConfig
from openfly_agent.eval.run import run
from openfly_agent.model.config import BinsActionHeadConfig, CellGroundingConfig, TinyVitVisionConfig
from openfly_agent.rollout.record import EpisodeRecord
from openfly_agent.sim.base import EpisodeSpec, Observation, StepInfo
from openfly_agent.sim.dynamics import rollout_array, step_motion
from openfly_agent.sim.occupancy import OccupancyGrid
from openfly_agent.sim.scene import SceneBounds
from openfly_agent.utils.geometry import Pose


def make_episode(
    episode_id: str, actions, start=(0.0, 0.0, 30.0, 0.0), scene_id: str = "scene-a", split=None
) -> Episode:
    """An episode whose positions are exactly the dynamics replay of `actions` (end them with STOP)."""
    poses = rollout_array(Pose(*start), actions)[:-1]  # (T, 4): the pose at which each action is taken
    return Episode(
        episode_id=episode_id,
        scene_id=scene_id,
        instruction=f"fly the route of {episode_id}",
        actions=np.asarray(actions),
        positions=poses[:, :3],
        yaws=poses[:, 3],
        frame_ids=[f"{episode_id}_{t}" for t in range(len(actions))],
        split=split,
        landmark_ids=[f"{scene_id}-lm0"],
    )


def wall_grid(x_from: float) -> OccupancyGrid:
    """Occupied for x >= `x_from` (a wall across the whole scene), free elsewhere; 1 m voxels."""
    bounds = SceneBounds(-200.0, 200.0, -200.0, 200.0, -10.0, 200.0)
    grid = OccupancyGrid.empty(bounds, 1.0)
    first = int(np.floor(x_from - bounds.xmin))
    grid.occupied[first:, :, :] = True
    return grid


class PoseSimulator:
    """Simulator protocol over the dynamics, with collisions from an occupancy grid (None = no obstacles)."""

    def __init__(self, grid: OccupancyGrid | None = None):
        self.grid = grid
        self.pose: Pose | None = None
        self.resets = 0

    def _obs(self) -> Observation:
        rgb = np.zeros((4, 4, 3), dtype=np.uint8)
        rgb[..., 0] = int(abs(self.pose.x)) % 256
        rgb[..., 1] = int(abs(self.pose.y)) % 256
        rgb[..., 2] = int(abs(self.pose.z)) % 256
        return Observation(rgb=rgb, pose=self.pose, boxes={})

    def reset(self, episode: EpisodeSpec) -> Observation:
        self.pose = episode.start
        self.resets += 1
        return self._obs()

    def step(self, action_id: int) -> tuple[Observation, StepInfo]:
        motion = step_motion(self.pose, action_id)
        collided = bool(
            self.grid is not None and self.grid.segment_collides(motion.start.position, motion.end.position)
        )
        self.pose = motion.end
        return self._obs(), StepInfo(action=action_id, collided=collided, done=action_id == C.ACTION_STOP)

    def close(self) -> None:
        return None


def generate_tiny_dataset(root, seed: int = 0, chained: bool = False) -> None:
    """A generated embedded dataset small enough for tests (~5 s): 2 scenes of 300 m, 64 px frames.

    Scene 0 gives train and test_seen episodes (half each), scene 1 (unseen seed) test_unseen; another `seed`
    gives other routes (other episode ids) in the same scenes. `chained`: every route past 2 landmarks, each
    frame's box its leg's target (the long-route benchmark's labels).
    """
    from openfly_agent.toolchain.config import (
        CategoryConfig,
        GenerateConfig,
        RenderConfig,
        RouteConfig,
        SceneConfig,
    )
    from openfly_agent.toolchain.generate import generate

    scenes = SceneConfig(
        city_size_m=300, city_buildings=30, train_seeds=[0], unseen_seeds=[1], trajectories_per_scene=8,
        test_seen_fraction=0.5,
    )  # fmt: skip
    route = RouteConfig(
        height_min_m=10, height_max_m=40, min_dist_m=40, max_dist_m=90, with_turn_prob=0.3,
        chain_prob=1.0 if chained else RouteConfig.chain_prob,
    )  # fmt: skip
    cfg = GenerateConfig(
        output_dir=str(root), seed=seed, workers=1, scenes=scenes, route=route, plots=False,
        categories=CategoryConfig(height_bins_m=[25, 40], length_bins_m=[50, 100]),
        render=RenderConfig(width=64, height=64, box_target="leg" if chained else "final"),
    )  # fmt: skip
    generate(cfg, progress=False)


def oracle_flights(tmp_path: Path, split: str, chained: bool = False) -> tuple[Path, Path]:
    """A tiny generated dataset (`tmp_path/dataset`; `chained`: every route past 2 landmarks) and the oracle's
    eval.py flights of `split` on it: the dataset and the policy folder (`tmp_path/eval/oracle`)."""
    dataset = tmp_path / "dataset"
    generate_tiny_dataset(dataset, chained=chained)
    run(
        EvalConfig(
            dataset_root=str(dataset), output_dir=str(tmp_path / "eval"), policy="oracle", split=[split]
        )
    )
    return dataset, tmp_path / "eval" / "oracle"


def small_agent_config():
    """The tiny model preset shrunk further (56 px, 2 blocks of width 32/48, a 2-layer LM of width 64)."""
    from openfly_agent.model.config import MemoryConfig, TinyLLMConfig, tiny_config

    return tiny_config(
        vision=TinyVitVisionConfig(
            image_size=56, patch_size=14, width=32, fused_width=48, depth=3, num_heads=2
        ),
        llm=TinyLLMConfig(hidden_size=64, num_layers=2, num_heads=2, intermediate_size=128),
        grounding=CellGroundingConfig(dim=32, num_heads=2),
        memory=MemoryConfig(capacity=2, grid=2),
    )


def save_small_agent(folder, texts, seed: int = 0) -> None:
    """A freshly initialised small agent (random weights, BPE tokenizer on `texts`) saved as a checkpoint."""
    import torch

    from openfly_agent.model.agent import OpenFlyAgent
    from openfly_agent.model.language.tokenizer import train_bpe_tokenizer

    tokenizer = train_bpe_tokenizer(list(texts) * 2, vocab_size=320, out_dir=None)
    torch.manual_seed(seed)
    agent = OpenFlyAgent.from_model_config(small_agent_config(), tokenizer=tokenizer).eval()
    with torch.no_grad():  # the untrained head says "visible": the records hold boxes the tests can compare
        agent.network.grounding_head.visibility.bias.fill_(2.0)
    agent.save_pretrained(str(folder))


NORM_STATS = {
    "vlnv1": {"action": {"q01": [0.0] * 8, "q99": [1, 9, 15, 15, 2, 2, 5, 5]}},
    "vln_norm": {"action": {"q01": [0.0] * 8, "q99": [1, 5, 15, 15, 2, 0, 5, 5]}},
}


def save_released_format_agent(folder, texts, seed: int = 0):
    """A small `openvla_compat` agent exported as a released OpenVLA-format folder.

    Writes `model.safetensors` in the OpenVLA key layout (no new modules), `config.json` with
    `model_type: openvla` and two norm-stats profiles, the tokenizer, and `model.yaml` (its ModelConfig).
    Returns the in-memory agent.
    """
    import dataclasses
    import json
    from pathlib import Path

    import torch
    import yaml
    from safetensors.torch import save_file

    from openfly_agent.model.agent import OpenFlyAgent
    from openfly_agent.model.config import HistoryEncodingConfig, MemoryConfig, PromptConfig
    from openfly_agent.model.language.tokenizer import train_bpe_tokenizer
    from openfly_agent.model.persistence.openvla_loader import to_openvla_state_dict
    from openfly_agent.utils.config import config_to_dict

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    tokenizer = train_bpe_tokenizer(list(texts) * 2, vocab_size=320, out_dir=None)
    cfg = dataclasses.replace(
        small_agent_config(),
        memory=MemoryConfig(capacity=2, grid=4, encoding=HistoryEncodingConfig()),
        prompt=PromptConfig(template="{instruction}", suffix_token_id=5),
        action_head=BinsActionHeadConfig(unnorm_key="vlnv1", decode_rule="nearest"),
    )
    torch.manual_seed(seed)
    agent = OpenFlyAgent.from_model_config(cfg, tokenizer=tokenizer, norm_stats=NORM_STATS).eval()
    state = {k: v.contiguous() for k, v in to_openvla_state_dict(agent).items()}
    save_file(state, str(folder / "model.safetensors"))
    (folder / "config.json").write_text(json.dumps({"model_type": "openvla", "norm_stats": NORM_STATS}))
    tokenizer.save_pretrained(str(folder))
    (folder / "model.yaml").write_text(yaml.safe_dump(config_to_dict(cfg)))
    return agent


def eval_main():
    """`eval.py`'s `main(argv)`, loaded from the repository's entry point (its exit code, in this process)."""
    spec = importlib.util.spec_from_file_location(
        "eval_entry_point", Path(__file__).resolve().parents[1] / "eval.py"
    )
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module.main


def success_record(
    episode_id: str, success: bool, split: str = "test_seen", goal=(100.0, 0.0, 10.0)
) -> EpisodeRecord:
    """One forward move and STOP: at the goal (success under both profiles) or 90 m short of it."""
    end = 100.0 if success else 10.0
    return EpisodeRecord(
        split=split,
        episode_id=episode_id,
        scene_id="s",
        policy="agent",
        instruction="fly to the tower",
        goal=list(goal),
        reference_path=[[0.0, 0.0, 10.0], [100.0, 0.0, 10.0]],
        actions=[1, 0],
        poses=[[0.0, 0.0, 10.0, 0.0], [end, 0.0, 10.0, 0.0], [end, 0.0, 10.0, 0.0]],
        stopped=True,
        end_reason="stop",
    )


PAIRED_IDENTITY = {
    "policy": "agent",
    "dataset_root": "outputs/datasets/x",
    "reader": ["trim", "first"],
    "max_steps": 100,
    "sim_type": "embedded",
    "sim_width": None,
    "sim_height": None,
    "sim_occupancy": None,
    "checkpoint": "ckpt",
    "unnorm_key": None,
    "decode_rule": None,
}


def policy_folder(root: Path, successes: dict[str, bool], split: str = "test_seen", **identity) -> Path:
    """`root/agent`, an eval policy folder: run_identity.json (`identity` overrides) and one `success_record` of
    `split` per episode id (True: a success under both profiles)."""
    from openfly_agent.eval.run import RUN_IDENTITY_NAME

    folder = root / "agent"
    folder.mkdir(parents=True)
    (folder / RUN_IDENTITY_NAME).write_text(json.dumps({**PAIRED_IDENTITY, **identity}))
    lines = [success_record(eid, ok, split).to_json() for eid, ok in successes.items()]
    (folder / "episodes.jsonl").write_text("\n".join(lines) + "\n")
    return folder
