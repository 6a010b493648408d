"""DAgger rounds with the trained agent in the loop: fly it in the train cities, label every visited state with
the A* expert, and write the labelled episodes as a dataset that training aggregates with the expert data.

Each rollout starts at the start pose of a train episode, with its instruction, in lockstep batches (the rollout
layer's `LockstepRunner`, one batched policy call per step, with the `ExpertLabelling` hook). At every visited
state the A* expert (`AStarExpert`, re-planned to the episode's goal
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
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from openfly_agent import constants as C
from openfly_agent.data.config import ReaderOptions
from openfly_agent.data.openfly_reader import load_openfly_dataset
from openfly_agent.data.schema import Episode
from openfly_agent.data.writer import OpenFlyDatasetWriter
from openfly_agent.rollout.policy import Policy
from openfly_agent.rollout.runner import LockstepRunner, RolloutHook, RunningEpisode
from openfly_agent.sim import dynamics
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

_ROLLOUT, _EXPERT = "dagger_rollout", "dagger_expert"  # ExpertLabelling's keys in RunningEpisode.state


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


class ExpertLabelling(RolloutHook):
    """The runner hook of a DAgger round: the A* expert labels every visited state and flies when the agent may not.

    Before the agent acts the current state is recorded with the expert's label; the expert's STOP (or a state
    without a plan, or more than `max_steps` states) ends the rollout. The agent proposes the action for its first
    `max_policy_steps` states; the expert's label is flown instead with probability `expert_mix`, and whenever
    the agent's action would stop, move sideways or hit the dilated map. Finished rollouts go to `on_rollout`
    (in completion order); dropped ones are logged.

    Args:
        make_expert: the A* expert of an episode (re-plans to its goal from any pose).
        on_rollout: called with each finished `DaggerRollout`.
        expert_mix: probability that the expert's action is executed instead of the agent's.
        max_policy_steps: states the agent may fly at most before the expert takes over.
        max_steps: states at most; a rollout that has not stopped by then is dropped.
        seed: seed of the expert-mix draws.
    """

    def __init__(
        self,
        make_expert: Callable[[Episode], AStarExpert],
        on_rollout: Callable[[DaggerRollout], None],
        expert_mix: float,
        max_policy_steps: int,
        max_steps: int,
        seed: int = 0,
    ):
        self.make_expert, self.on_rollout = make_expert, on_rollout
        self.expert_mix, self.max_policy_steps, self.max_steps = expert_mix, max_policy_steps, max_steps
        self.rng = np.random.default_rng(seed)

    def on_episode_start(self, running: RunningEpisode) -> None:
        running.state[_ROLLOUT] = DaggerRollout(running.episode)
        running.state[_EXPERT] = self.make_expert(running.episode)

    def before_act(self, running: RunningEpisode) -> bool:
        """Record the current state with the expert's label; True when the rollout ends here."""
        rollout, obs = running.state[_ROLLOUT], running.obs
        try:
            label = running.state[_EXPERT].action(obs.pose)
        except PlanningFailed as err:
            rollout.failed = f"expert_failed: {err}"
            return True
        rollout.poses.append(obs.pose)
        rollout.labels.append(int(label))
        rollout.frames.append(np.ascontiguousarray(obs.rgb))
        box = running.target_box()
        rollout.boxes.append(None if box is None else np.asarray(box, dtype=np.float64))
        return rollout.done or len(rollout.labels) > self.max_steps

    def asks_policy(self, running: RunningEpisode) -> bool:
        return running.state[_ROLLOUT].agent_steps < self.max_policy_steps

    def choose_action(self, running: RunningEpisode, proposed: int | None) -> int:
        """The action flown from the current state: the agent's unless mixed out, blocked or an early STOP."""
        rollout = running.state[_ROLLOUT]
        label = rollout.labels[-1]
        if proposed is None:  # the agent's budget is spent: the expert flies
            return label
        rollout.agent_steps += 1
        if self.rng.random() < self.expert_mix or proposed in (
            C.ACTION_STOP, C.ACTION_MOVE_LEFT, C.ACTION_MOVE_RIGHT,
        ):  # fmt: skip
            return label
        pose = running.obs.pose
        blocked = running.state[_EXPERT].astar.segment_blocked(
            pose.position, dynamics.apply_action(pose, int(proposed)).position
        )
        return label if blocked else int(proposed)

    def on_episode_end(self, running: RunningEpisode) -> None:
        rollout = running.state.get(_ROLLOUT) or DaggerRollout(running.episode, failed=running.record.error)
        if rollout.failed is None and len(rollout.labels) > self.max_steps:
            rollout.failed = f"no STOP within {self.max_steps} states"
        if rollout.failed is None and not rollout.done:
            rollout.failed = f"ended by the simulator ({running.record.end_reason})"
        if rollout.failed is not None:
            logger.info("dagger rollout of %s dropped: %s", rollout.source.episode_id, rollout.failed)
            return
        self.on_rollout(rollout)


def run_dagger_round(policy: Policy, cfg: DaggerRoundConfig, progress: bool = True) -> dict:
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

        def write(rollout: DaggerRollout) -> None:
            nonlocal written
            episode = rollout_episode(rollout, index_of[rollout.source.episode_id], cfg.round_name)
            writer.write_episode(episode, rollout.frames)
            written += 1

        labelling = ExpertLabelling(
            make_expert, write, cfg.expert_mix, cfg.max_policy_steps, cfg.max_steps, seed=cfg.seed
        )
        with VectorSimulator.embedded(sim_cfg, num_envs=cfg.num_envs) as env:
            # the runner's cap is never met: the labelling ends a rollout once it has max_steps + 1 states
            runner = LockstepRunner(
                policy, env, cfg.max_steps + 1, [labelling], whole_groups=False, show_progress=progress
            )
            runner.run([e for _, e in todo], C.SPLIT_TRAIN)
        dropped = len(todo) - written
    writer.finalize()
    return {"round": cfg.round_name, "rollouts": len(chosen), "written": written, "dropped": dropped}


def _written_id(episode: Episode, round_name: str, index: int) -> str:
    folder = f"{episode.episode_id.rsplit('/', 1)[-1]}_{round_name}_{index}"
    return f"{episode.scene_id}/astar_data/{episode.category or 'dagger'}/{folder}"
