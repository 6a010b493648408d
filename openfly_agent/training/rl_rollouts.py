"""The RL stage's rollouts: G sampled flights of the agent from the same start and instruction, through the one
rollout layer (`LockstepRunner` over any `VectorSimulator`: the embedded city or a bridge), each step recorded as
a training sample, each flight rewarded by the simulator's own metrics (rollout/metrics.py under a profile).

A step's sample replays what the policy saw: the frame, the instruction, the keyframe sets its memory held (their
frames and the boxes it predicted for them), the box it predicted (the box token's input) and the action it took
(the label); the simulator's true target box is the grounding target.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
import torch

from openfly_agent import constants as C
from openfly_agent.data.schema import Episode
from openfly_agent.model.session import AgentSession
from openfly_agent.rollout.agent import AgentPolicy
from openfly_agent.rollout.metrics import episode_metrics, trajectory_of
from openfly_agent.rollout.profiles import MetricProfile
from openfly_agent.rollout.record import EpisodeRecord
from openfly_agent.rollout.runner import LockstepRunner, RolloutHook, RunningEpisode, box_list
from openfly_agent.sim.vector import VectorSimulator
from openfly_agent.training.config import RLConfig

GROUP_SEPARATOR = (
    "#rl"  # a rollout's episode id: <source id>#rl<g>, so the G flights of a group run side by side
)


@dataclass
class RolloutStep:
    """What the policy saw and did at one step (memory: frame indices of its keyframe sets, oldest first)."""

    rgb: np.ndarray  # (H, W, 3) uint8
    action: int
    predicted_box: list[float] | None  # what the box token embedded (None: predicted invisible)
    true_box: list[float] | None  # the simulator's box of the target (None: not in view)
    boxes_known: bool  # the simulator reports landmark boxes (an engine without them: no grounding target)
    memory: list[list[int]] = field(default_factory=list)


@dataclass
class Rollout:
    """One flight of a group: its record, its steps, its reward and whether it succeeded under the profile."""

    group: int
    record: EpisodeRecord
    steps: list[RolloutStep]
    reward: float = 0.0
    success: bool = False


class StepRecorder(RolloutHook):
    """Keeps every step of every episode (`RolloutStep`) and hands each finished one to `on_end`."""

    def __init__(self, on_end) -> None:
        self.on_end = on_end

    def on_episode_start(self, running: RunningEpisode) -> None:
        running.state[StepRecorder] = ([], [])  # the steps so far, the memory's keyframe sets after the last

    def on_step(self, running: RunningEpisode, action: int) -> None:
        steps, memory = running.state[StepRecorder]
        steps.append(
            RolloutStep(
                rgb=np.array(running.obs.rgb, copy=True),
                action=int(action),
                predicted_box=box_list(running.detail.get("box")),
                true_box=running.target_box(),
                boxes_known=running.obs.boxes is not None,
                memory=[list(s) for s in memory],  # what the memory held when this step read it
            )
        )
        running.state[StepRecorder] = (steps, running.detail.get("keyframes") or [])

    def on_episode_end(self, running: RunningEpisode) -> None:
        steps, _ = running.state.pop(StepRecorder)
        self.on_end(running.record, steps)


def group_episodes(sources: Sequence[Episode], group_size: int) -> list[Episode]:
    """Each source episode `group_size` times, with ids `<id>#rl<g>`, group after group."""
    return [
        dataclasses.replace(source, episode_id=f"{source.episode_id}{GROUP_SEPARATOR}{g}")
        for source in sources
        for g in range(group_size)
    ]


def rollout_reward(record: EpisodeRecord, profile: MetricProfile, rl: RLConfig) -> tuple[float, bool]:
    """The reward of a finished flight and its success: 1 for success under `profile` (`episode_metrics`), plus
    the shaping terms of `rl` that are on (progress toward the goal, a collision, a STOP outside the radius)."""
    trajectory = trajectory_of(record)
    row = episode_metrics(trajectory, profile)
    reward = float(row["success"])
    if rl.progress_weight:
        dims = profile.distance_dims
        start = float(np.linalg.norm(trajectory.positions[0, :dims] - trajectory.goal[:dims]))
        reward += rl.progress_weight * (start - row["ne"]) / max(start, 1e-6)
    if rl.collision_penalty and row["collided"]:
        reward -= rl.collision_penalty
    if rl.far_stop_penalty and row["stopped"] and not profile.within(row["ne"]):
        reward -= rl.far_stop_penalty
    return reward, bool(row["success"])


def collect_groups(
    agent,
    env: VectorSimulator,
    sources: Sequence[Episode],
    rl: RLConfig,
    profile: MetricProfile,
    generator: torch.Generator,
    max_steps: int,
    show_progress: bool = False,
) -> list[list[Rollout]]:
    """Fly `rl.group_size` sampled rollouts of `agent` (eval mode) from each of `sources`; one list per source, in
    order, each in group order. The actions are drawn from `generator` (the same state gives the same flights)."""
    session = AgentSession(agent, temperature=rl.temperature, generator=generator)
    policy = AgentPolicy(session, name="rl")
    episodes = group_episodes(sources, rl.group_size)
    index = {episode.episode_id: i for i, episode in enumerate(episodes)}
    rollouts: list[Rollout | None] = [None] * len(episodes)

    def keep(record: EpisodeRecord, steps: list[RolloutStep]) -> None:
        i = index[record.episode_id]
        reward, success = rollout_reward(record, profile, rl)
        rollouts[i] = Rollout(i // rl.group_size, record, steps, reward, success)

    runner = LockstepRunner(policy, env, max_steps, [StepRecorder(keep)], show_progress=show_progress)
    runner.run(episodes, C.SPLIT_TRAIN)
    done = [r for r in rollouts if r is not None]
    return [done[i : i + rl.group_size] for i in range(0, len(done), rl.group_size)]


def step_sample(record: EpisodeRecord, steps: list[RolloutStep], t: int) -> dict:
    """Step `t` of a flight as a `NavigationStepDataset` sample (data/dataset.py) the collator batches, plus the
    box token's input (`TOKEN_BOX`, `TOKEN_BOX_VISIBLE`)."""
    step = steps[t]

    def box(value: list[float] | None) -> tuple[np.ndarray, bool]:
        return (np.zeros(4, np.float32), False) if value is None else (np.asarray(value, np.float32), True)

    memory = [[(steps[j].rgb, *box(steps[j].predicted_box)) for j in frame_set] for frame_set in step.memory]
    target, visible = box(step.true_box)
    token, token_visible = box(step.predicted_box)
    return {
        C.OBS_INSTRUCTION: record.instruction,
        C.OBS_RGB: step.rgb,
        C.MEMORY: memory,
        C.ACTION: step.action,
        C.BOX: target,
        C.BOX_VISIBLE: visible,
        C.TOKEN_BOX: token,
        C.TOKEN_BOX_VISIBLE: token_visible,
        C.EPISODE_ID: record.episode_id,
        C.STEP_INDEX: t,
    }
