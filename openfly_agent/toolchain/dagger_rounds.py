"""DAgger rounds with the trained agent in the loop: fly it in the train cities, label every visited state with
the A* expert, and write the labelled episodes as a dataset that training aggregates with the expert data.

Each rollout starts at the start pose of a train episode, with its instruction, in lockstep batches (one batched
policy call per step). At every visited state the A* expert (`AStarExpert`, re-planned to the episode's goal
from wherever the agent is) gives the label; the executed action is the agent's, or the expert's with
probability `expert_mix` (a beta-mixture), and always the expert's when the agent's action would hit an obstacle
or stop early. After `max_policy_steps` steps the expert flies the rest of the way, so every episode ends with
the expert's STOP, given at every state within `stop_radius_m` of the goal (the A* plan alone stops only within
its 3-m tolerance, so rollouts that reach the goal area would teach the agent to fly on past it). The written
episodes keep the source episode's instruction, target and camera pitch; `positions[t + 1]` follows the executed
action, not the label (that is the point of the relabelling).
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Protocol

import numpy as np
from tqdm.auto import tqdm

from openfly_agent import constants as C
from openfly_agent.data.config import ReaderOptions
from openfly_agent.data.openfly_reader import load_openfly_dataset
from openfly_agent.data.schema import Episode
from openfly_agent.data.writer import OpenFlyDatasetWriter
from openfly_agent.sim import dynamics
from openfly_agent.sim.base import EpisodeSpec, Observation
from openfly_agent.sim.city import parse_scene_id
from openfly_agent.sim.embedded import EmbeddedSimConfig
from openfly_agent.sim.vector import VectorSimulator
from openfly_agent.toolchain.astar import PlanningFailed
from openfly_agent.toolchain.config import DaggerRoundConfig, GenerateConfig
from openfly_agent.toolchain.dagger import AStarExpert
from openfly_agent.toolchain.pipeline import PreparedScene, prepare_scene
from openfly_agent.toolchain.scenes import city_config_for, embedded_scene
from openfly_agent.utils.config import load_yaml_config
from openfly_agent.utils.geometry import Pose

logger = logging.getLogger(__name__)

OBS_STEP = "step"


class BatchPolicy(Protocol):
    """A batched closed-loop policy (the evaluation `Policy` protocol: the agent's adapter implements it)."""

    def reset(self, episode_ids: list[str]) -> None: ...

    def act(self, observations: list[dict]) -> list[int]: ...


@dataclass
class DaggerRollout:
    """One relabelled rollout: visited poses, the expert's label at each, frames and target boxes."""

    source: Episode
    poses: list[Pose] = field(default_factory=list)
    labels: list[int] = field(default_factory=list)
    frames: list[np.ndarray] = field(default_factory=list)
    boxes: list[np.ndarray | None] = field(default_factory=list)
    agent_steps: int = 0  # states where the agent chose the executed action
    failed: str | None = None  # why the rollout has no usable end (expert without a plan), else None

    @property
    def done(self) -> bool:
        return self.failed is not None or (bool(self.labels) and self.labels[-1] == C.ACTION_STOP)


@dataclass
class _Slot:
    rollout: DaggerRollout
    expert: AStarExpert
    obs: Observation
    episode_id: str


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
    )


def collect_rollouts(
    policy: BatchPolicy,
    episodes: Sequence[Episode],
    make_expert: Callable[[Episode], AStarExpert],
    env,
    expert_mix: float,
    max_policy_steps: int,
    max_steps: int,
    seed: int = 0,
    progress: bool = True,
):
    """Yield one `DaggerRollout` per episode as it finishes (in completion order).

    Args:
        policy: the agent (batched `reset` / `act` on observation dicts: episode_id, instruction, rgb, pose, step).
        episodes: train episodes whose start pose, instruction, goal and target landmark are used.
        make_expert: the A* expert of an episode (re-plans to its goal from any pose).
        env: lockstep environments with `num_envs`, `reset_env(slot, spec)`, `step(actions)` (a
            `VectorSimulator` of embedded simulators that do not end episodes on collision).
        expert_mix: probability that the expert's action is executed instead of the agent's.
        max_policy_steps: states the agent may fly at most before the expert takes over.
        max_steps: states at most; a rollout that has not stopped by then is dropped.
        seed: seed of the expert-mix draws.
    """
    rng = np.random.default_rng(seed)
    queue = list(episodes)
    slots: list[_Slot | None] = [None] * env.num_envs
    bar = tqdm(total=len(queue), desc="dagger rollouts", disable=not progress, leave=False)
    try:
        while queue or any(s is not None for s in slots):
            for i in range(env.num_envs):  # refill idle slots
                while slots[i] is None and queue:
                    slots[i] = _start(env, i, queue.pop(0), make_expert, policy)
            active = [i for i, s in enumerate(slots) if s is not None]
            for i in active:
                _label(slots[i])
            finished = [
                i for i in active if slots[i].rollout.done or len(slots[i].rollout.labels) > max_steps
            ]
            for i in finished:
                yield from _finish(slots[i], policy, max_steps)
                slots[i] = None
                bar.update(1)
            active = [i for i in active if slots[i] is not None]
            if not active:
                continue
            flying = [i for i in active if slots[i].rollout.agent_steps < max_policy_steps]
            proposed = (
                dict(zip(flying, policy.act([_policy_obs(slots[i]) for i in flying]))) if flying else {}
            )
            actions: list[int | None] = [None] * env.num_envs
            for i in active:
                actions[i] = _executed(slots[i], proposed.get(i), expert_mix, rng)
            observations, _ = env.step(actions)
            for i in active:
                slots[i].obs = observations[i]
    finally:
        bar.close()


def _start(env, slot: int, episode: Episode, make_expert, policy) -> _Slot:
    x, y, z = (float(v) for v in episode.positions[0])
    spec = EpisodeSpec(
        episode_id=f"dagger/{episode.episode_id}",
        scene_id=episode.scene_id,
        start=Pose(x, y, z, float(episode.yaws[0])),
        goal=np.asarray(episode.goal, dtype=np.float64),
        pitch_deg=float(episode.pitch_deg),
        landmark_id=episode.landmark_ids[-1] if episode.landmark_ids else None,
    )
    policy.reset([spec.episode_id])
    obs = env.reset_env(slot, spec)
    return _Slot(DaggerRollout(episode), make_expert(episode), obs, spec.episode_id)


def _label(slot: _Slot) -> None:
    """Record the current state with the expert's label (or mark the rollout failed)."""
    rollout, obs = slot.rollout, slot.obs
    try:
        label = slot.expert.action(obs.pose)
    except PlanningFailed as err:
        rollout.failed = f"expert_failed: {err}"
        return
    target = rollout.source.landmark_ids[-1] if rollout.source.landmark_ids else None
    rollout.poses.append(obs.pose)
    rollout.labels.append(int(label))
    rollout.frames.append(np.ascontiguousarray(obs.rgb))
    box = (obs.boxes or {}).get(target) if target else None
    rollout.boxes.append(None if box is None else np.asarray(box, dtype=np.float64))


def _policy_obs(slot: _Slot) -> dict:
    return {
        C.EPISODE_ID: slot.episode_id,
        C.OBS_INSTRUCTION: slot.rollout.source.instruction,
        C.OBS_RGB: slot.obs.rgb,
        C.OBS_POSE: slot.obs.pose.as_array(),
        OBS_STEP: len(slot.rollout.labels) - 1,
    }


def _executed(slot: _Slot, proposed: int | None, expert_mix: float, rng: np.random.Generator) -> int:
    """The action flown from the current state: the agent's unless mixed out, blocked or an early STOP."""
    label = slot.rollout.labels[-1]
    if proposed is None:  # the agent's budget is spent: the expert flies
        return label
    slot.rollout.agent_steps += 1
    if rng.random() < expert_mix or proposed in (C.ACTION_STOP, C.ACTION_MOVE_LEFT, C.ACTION_MOVE_RIGHT):
        return label
    pose = slot.obs.pose
    if slot.expert.astar.segment_blocked(pose.position, dynamics.apply_action(pose, int(proposed)).position):
        return label
    return int(proposed)


def _finish(slot: _Slot, policy, max_steps: int):
    policy.reset([slot.episode_id])
    rollout = slot.rollout
    if rollout.failed is None and len(rollout.labels) > max_steps:
        rollout.failed = f"no STOP within {max_steps} states"
    if rollout.failed is not None:
        logger.info("dagger rollout of %s dropped: %s", rollout.source.episode_id, rollout.failed)
        return
    yield rollout


def run_dagger_round(policy: BatchPolicy, cfg: DaggerRoundConfig, progress: bool = True) -> dict:
    """One DAgger round: `cfg.episodes` rollouts of `policy` from train episodes of `cfg.source_root`, written as
    a dataset under `cfg.output_dir` (resumable: rollouts already written are skipped). Returns counts."""
    source = Path(cfg.source_root)
    generate_cfg = load_yaml_config(GenerateConfig, source / C.TOOLCHAIN_CONFIG_JSON, [])
    train = load_openfly_dataset(source, C.SPLIT_TRAIN, ReaderOptions(takeoff_landing="trim"))
    rng = np.random.default_rng(cfg.seed)
    picks = sorted(rng.choice(len(train), min(cfg.episodes, len(train)), replace=False).tolist())
    chosen = sorted(((i, train[i]) for i in picks), key=lambda item: (item[1].scene_id, item[0]))
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
        goal = np.asarray(episode.goal, dtype=np.float64)
        return AStarExpert(
            prepared[episode.scene_id].astar, [goal], reuse_plans=False, stop_radius_m=cfg.stop_radius_m
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
        with VectorSimulator.embedded(sim_cfg, num_envs=cfg.num_envs) as env:
            for rollout in collect_rollouts(
                policy, [e for _, e in todo], make_expert, env, cfg.expert_mix, cfg.max_policy_steps,
                cfg.max_steps, seed=cfg.seed, progress=progress,
            ):  # fmt: skip
                episode = rollout_episode(rollout, index_of[rollout.source.episode_id], cfg.round_name)
                writer.write_episode(episode, rollout.frames)
                written += 1
        dropped = len(todo) - written
    writer.finalize()
    return {"round": cfg.round_name, "rollouts": len(chosen), "written": written, "dropped": dropped}


def _written_id(episode: Episode, round_name: str, index: int) -> str:
    folder = f"{episode.episode_id.rsplit('/', 1)[-1]}_{round_name}_{index}"
    return f"{episode.scene_id}/astar_data/{episode.category or 'dagger'}/{folder}"
