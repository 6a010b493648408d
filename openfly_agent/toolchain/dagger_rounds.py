"""DAgger rounds with the trained agent in the loop: fly it in the train cities, label every visited state with
the A* expert, and write the labelled episodes as a dataset that training aggregates with the expert data.

Each rollout starts at the start pose of a train episode, with its instruction, in lockstep batches (the rollout
layer's `LockstepRunner`, one batched policy call per step, with the `ExpertLabelling` hook of toolchain/expert.py
that generation-time DAgger uses too). At every visited state the A* expert (`AStarExpert`, re-planned from
wherever the agent is to the episode's goal, through each leg's goal in order where the episodes give them) gives
the label; the executed action is the agent's, or the expert's with probability `expert_mix` (a beta-mixture),
and always the expert's when the agent's action would hit an obstacle or stop early. After `max_policy_steps`
steps the expert flies the rest of the way, so every episode ends with the expert's STOP, given at every state
within `stop_radius_m` of the goal (the A* plan alone stops only within its 3-m tolerance, so rollouts that reach
the goal area would teach the agent to fly on past it). The written episodes keep the source episode's
instruction, targets, goals and camera pitch, and each state's box is that of the landmark the source dataset's
`render.box_target` names (the expert's current leg's target for `leg`); `positions[t + 1]` follows the executed
action, not the label (that is the point of the relabelling).
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from openfly_agent import constants as C
from openfly_agent.data.config import ReaderOptions
from openfly_agent.data.openfly_reader import load_openfly_dataset
from openfly_agent.data.schema import Episode
from openfly_agent.data.writer import OpenFlyDatasetWriter
from openfly_agent.rollout.policy import Policy
from openfly_agent.rollout.runner import LockstepRunner
from openfly_agent.sim.city import parse_scene_id
from openfly_agent.sim.embedded import EmbeddedSimConfig
from openfly_agent.sim.vector import VectorSimulator
from openfly_agent.toolchain.config import BOX_TARGET_LEG, DaggerRoundConfig, GenerateConfig
from openfly_agent.toolchain.expert import AStarExpert, DaggerRollout, ExpertLabelling
from openfly_agent.toolchain.pipeline import PreparedScene, prepare_scene
from openfly_agent.toolchain.scenes import city_config_for, embedded_scene
from openfly_agent.utils.config import load_yaml_config

logger = logging.getLogger(__name__)


def rollout_episode(rollout: DaggerRollout, index: int, round_name: str) -> Episode:
    """The written form of a finished rollout (same scene, category, instruction and target as its source)."""
    source = rollout.source
    boxes = np.zeros((len(rollout.poses), 4))
    visible = np.zeros(len(rollout.poses), dtype=bool)
    for t, box in enumerate(rollout.boxes):
        if box is not None:
            boxes[t], visible[t] = box, True
    episode_id = _written_id(source, round_name, index)
    folder, category = episode_id.rsplit("/", 1)[-1], source.category or "dagger"
    return Episode(
        episode_id=episode_id,
        scene_id=source.scene_id,
        instruction=source.instruction,
        actions=np.asarray(rollout.labels, dtype=np.int64),
        positions=np.array([p.position for p in rollout.poses]),
        yaws=np.array([p.yaw for p in rollout.poses]),
        frame_ids=[f"{folder}_{t}" for t in range(len(rollout.poses))],
        split=C.SPLIT_TRAIN,
        category=category,
        pitch_deg=source.pitch_deg,
        boxes=boxes,
        box_visible=visible,
        landmark_ids=list(source.landmark_ids),
        goal=np.asarray(source.goal, dtype=np.float64),
        leg_goals=None if source.leg_goals is None else np.asarray(source.leg_goals, dtype=np.float64),
    )


def run_dagger_round(policy: Policy, cfg: DaggerRoundConfig, progress: bool = True) -> dict:
    """One DAgger round: `cfg.episodes` rollouts of `policy` from train episodes of `cfg.source_root`, written as
    a dataset under `cfg.output_dir` (resumable: rollouts already written are skipped). Returns counts."""
    source = Path(cfg.source_root)
    generate_cfg = load_yaml_config(GenerateConfig, source / C.TOOLCHAIN_CONFIG_JSON, [])
    train = load_openfly_dataset(source, C.SPLIT_TRAIN, ReaderOptions(takeoff_landing="trim"))
    rng = np.random.default_rng(cfg.seed)
    picks = sorted(rng.choice(len(train), min(cfg.episodes, len(train)), replace=False).tolist())
    chosen = sorted(((i, train[i]) for i in picks), key=lambda item: (item[1].scene_id, item[0]))
    box_target = generate_cfg.render.box_target
    if box_target == BOX_TARGET_LEG:
        _check_leg_goals(source, [e for _, e in chosen])
    writer = OpenFlyDatasetWriter(cfg.output_dir)
    todo = [(i, e) for i, e in chosen if not writer.has_episode(_written_id(e, cfg.round_name, i))]
    logger.info("dagger %s: %d of %d rollouts to run", cfg.round_name, len(todo), len(chosen))
    prepared: dict[str, PreparedScene] = {}

    def make_expert(episode: Episode) -> AStarExpert:
        if episode.scene_id not in prepared:
            seed = parse_scene_id(episode.scene_id)
            prepared[episode.scene_id] = prepare_scene(
                embedded_scene(seed, generate_cfg.scenes), generate_cfg
            )
        return AStarExpert(
            prepared[episode.scene_id].astar,
            episode.route_goals,
            reuse_plans=False,
            stop_radius_m=cfg.stop_radius_m,
        )

    index_of = {e.episode_id: i for i, e in todo}
    written = dropped = 0
    if todo:
        sim_cfg = EmbeddedSimConfig(
            width=generate_cfg.render.width,
            height=generate_cfg.render.height,
            city=city_config_for(generate_cfg.scenes),
            collision="ignore",
            max_cached_scenes=max(4, cfg.num_envs),
        )

        def write(rollout: DaggerRollout) -> None:
            nonlocal written
            if rollout.failed is not None:
                logger.info(
                    "dagger rollout of %s dropped: %s (%s)",
                    rollout.source.episode_id,
                    rollout.failed,
                    rollout.detail,
                )
                return
            episode = rollout_episode(rollout, index_of[rollout.source.episode_id], cfg.round_name)
            writer.write_episode(episode, rollout.frames)
            written += 1

        labelling = ExpertLabelling(
            make_expert,
            write,
            max_policy_steps=cfg.max_policy_steps,
            max_steps=cfg.max_steps,
            expert_mix=cfg.expert_mix,
            label_in_observation=policy.features.expert_action,
            seed=cfg.seed,
            box_target=box_target,
        )
        with VectorSimulator.embedded(sim_cfg, num_envs=cfg.num_envs) as env:
            # the runner's cap is never met: the labelling ends a rollout at its (max_steps + 1)-th state
            runner = LockstepRunner(
                policy, env, cfg.max_steps + 1, [labelling], whole_groups=False, show_progress=progress
            )
            runner.run([e for _, e in todo], C.SPLIT_TRAIN)
        dropped = len(todo) - written
    writer.finalize()
    return {"round": cfg.round_name, "rollouts": len(chosen), "written": written, "dropped": dropped}


def _check_leg_goals(source: Path, episodes: list[Episode]) -> None:
    """A dataset whose boxes are each leg's target must give each leg's goal: the expert flies the route's legs
    (straight to the final goal it would label a shortcut the instruction does not describe)."""
    missing = [
        e.episode_id for e in episodes if e.leg_goals is None or len(e.leg_goals) != len(e.landmark_ids)
    ]
    if missing:
        raise ValueError(
            f"{source}: render.box_target is 'leg' but {len(missing)} train episodes (first: {missing[0]}) have no "
            "goal per leg (`leg_goals`, written by the toolchain since this field exists): regenerate the dataset"
        )


def _written_id(episode: Episode, round_name: str, index: int) -> str:
    folder = f"{episode.episode_id.rsplit('/', 1)[-1]}_{round_name}_{index}"
    return f"{episode.scene_id}/astar_data/{episode.category or 'dagger'}/{folder}"
