"""The one closed-loop runner: episodes in lockstep slots, one batched policy call per step, hooks around it.

At every step the policy gets the observations of the running episodes at once, the environment executes the
actions, and an episode that stops, hits the step cap or meets an engine error ends (its `EpisodeRecord` goes to
every hook's `on_episode_end`, then to the caller's `on_finish`). Hooks see each episode's start, each step and
its end, and may end an episode before the policy acts, add fields to its observation, keep the policy out of a
step or replace the action it chose (DAgger's expert labelling, in generation and in rounds).

Slots are refilled by `whole_groups` (evaluation): consecutive groups of `num_envs` episodes start together and
the next group starts when the last episode of this one has ended, so an episode's batch companions at every
step depend only on the episode list and the batch size (a group recomputed after a kill gives bit-identical
results; docs/EVAL.md), or, without it, each slot as soon as its episode ends (DAgger).
"""

from __future__ import annotations

import logging
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from openfly_agent import constants as C
from openfly_agent.data.schema import Episode
from openfly_agent.rollout.episodes import episode_spec, goal_of, reference_path, target_landmark
from openfly_agent.rollout.policy import (
    OBS_EPISODE_ID,
    OBS_STEP,
    OBS_TARGET_BOX,
    Policy,
    check_actions,
    step_details,
)
from openfly_agent.rollout.record import EpisodeRecord
from openfly_agent.sim.base import NO_FRAME, Observation
from openfly_agent.sim.vector import ENGINE_ERRORS, ERROR_KEY, VectorSimulator
from openfly_agent.utils.progress import progress_bar

logger = logging.getLogger(__name__)


@dataclass
class RolloutStats:
    """Counters of one `run` call; times in seconds (wall clock)."""

    episodes: int = 0
    steps: int = 0
    policy_calls: int = 0
    sim_s: float = 0.0
    policy_s: float = 0.0

    def add(self, other: RolloutStats) -> None:
        """Accumulate `other` into these counters."""
        for name in ("episodes", "steps", "policy_calls", "sim_s", "policy_s"):
            setattr(self, name, getattr(self, name) + getattr(other, name))


@dataclass
class RunningEpisode:
    """One episode in a slot: its dataset episode, current observation and record so far.

    `detail` is what the policy predicted besides the action at this step (`box`, `keyframes`; empty when the
    policy gives none or did not act); `state` is free for hooks (keyed by the hook's own name).
    """

    slot: int
    episode: Episode
    obs: Observation
    record: EpisodeRecord
    detail: dict = field(default_factory=dict)
    state: dict = field(default_factory=dict)

    def target_box(self) -> list[float] | None:
        """The simulator's (cx, cy, w, h) of the target landmark in the current frame, None when not visible."""
        return self.landmark_box(target_landmark(self.episode))

    def landmark_box(self, landmark: str | None) -> list[float] | None:
        """The simulator's (cx, cy, w, h) of `landmark` in the current frame, None when not visible (or None)."""
        return box_list((self.obs.boxes or {}).get(landmark)) if landmark else None


class RolloutHook:
    """Callbacks of `LockstepRunner`; each is a no-op here and a hook overrides what it needs."""

    def on_episode_start(self, running: RunningEpisode) -> None:
        """`running` has just started (its first observation is `running.obs`)."""

    def before_act(self, running: RunningEpisode) -> bool:
        """Called at each state before the policy acts; True ends the episode there (its record keeps
        `end_reason` `max_steps`: neither a STOP nor the simulator ended it; the hook knows why)."""
        return False

    def asks_policy(self, running: RunningEpisode) -> bool:
        """Whether the policy chooses this step's action (False: `choose_action` gets None)."""
        return True

    def observation_fields(self, running: RunningEpisode) -> dict:
        """Fields this hook adds to the policy's observation of `running` (e.g. the expert's label)."""
        return {}

    def choose_action(self, running: RunningEpisode, proposed: int | None) -> int:
        """The action executed: the policy's `proposed` one (None when it was not asked) or another."""
        return proposed

    def on_step(self, running: RunningEpisode, action: int) -> None:
        """`action` is about to be executed from `running.obs` (`running.detail`: the policy's predictions)."""

    def on_episode_end(self, running: RunningEpisode) -> None:
        """`running.record` is final."""


def box_list(box) -> list[float] | None:
    """A box as 4 floats, or None."""
    return None if box is None else [float(v) for v in np.asarray(box, dtype=np.float64).reshape(4)]


def new_record(episode: Episode, split: str, policy_name: str, start: list[float]) -> EpisodeRecord:
    """The record of `episode` before its first action, standing at `start` (x, y, z, yaw)."""
    return EpisodeRecord(
        split=split,
        episode_id=episode.episode_id,
        scene_id=episode.scene_id,
        policy=policy_name,
        instruction=episode.instruction,
        goal=[float(v) for v in goal_of(episode)],
        reference_path=reference_path(episode).tolist(),
        actions=[],
        poses=[[float(v) for v in start]],
        stopped=False,
        end_reason="max_steps",
    )


class LockstepRunner:
    """Runs episodes through `env` with `policy`.

    Args:
        policy: any `Policy`; its `features` decide what the observations carry.
        env: the lockstep environment; its `num_envs` is the batch size.
        max_steps: actions per episode at most (the official evaluation: 100).
        hooks: called in order at every event.
        whole_groups: refill slots by whole groups (evaluation) or each as soon as it is free.
        show_progress: draw a tqdm bar.
    """

    def __init__(
        self,
        policy: Policy,
        env: VectorSimulator,
        max_steps: int = C.MAX_EPISODE_STEPS,
        hooks: list[RolloutHook] | tuple[RolloutHook, ...] = (),
        whole_groups: bool = True,
        show_progress: bool = True,
    ):
        if max_steps < 1:
            raise ValueError(f"max_steps must be >= 1, got {max_steps}")
        self.policy, self.env, self.max_steps = policy, env, int(max_steps)
        self.hooks = list(hooks)
        self.whole_groups = whole_groups
        self.show_progress = show_progress
        self.stats = RolloutStats()

    def run(
        self,
        episodes: list[Episode],
        split: str,
        on_finish: Callable[[EpisodeRecord], None] | None = None,
    ) -> RolloutStats:
        """Run every episode of `episodes` to its end, in list order; as each ends, the hooks see it and then
        `on_finish(record)` gets its record (what the caller keeps of the run)."""
        stats = RolloutStats()
        queue = deque(episodes)
        slots: list[RunningEpisode | None] = [None] * self.env.num_envs
        bar = progress_bar(
            total=len(episodes),
            desc=f"{self.policy.name}/{split}",
            disable=not self.show_progress,
            leave=False,
        )

        def finish(slot: int) -> None:
            running, slots[slot] = slots[slot], None
            self.policy.reset([running.episode.episode_id])
            for hook in self.hooks:
                hook.on_episode_end(running)
            if on_finish is not None:
                on_finish(running.record)
            stats.episodes += 1
            bar.update(1)

        try:
            while queue or any(running is not None for running in slots):
                if not self.whole_groups or all(running is None for running in slots):
                    for slot in range(self.env.num_envs):
                        if slots[slot] is None and queue:
                            slots[slot] = self._start(slot, queue.popleft(), split, stats)
                            if slots[slot].record.end_reason == "error":
                                finish(slot)
                for slot in [i for i, running in enumerate(slots) if running is not None]:
                    if any(hook.before_act(slots[slot]) for hook in self.hooks):
                        finish(slot)
                active = [i for i, running in enumerate(slots) if running is not None]
                if active:
                    for slot in self._step([slots[i] for i in active], stats):
                        finish(slot)
        finally:
            bar.close()
        self.stats.add(stats)
        return stats

    def _start(self, slot: int, episode: Episode, split: str, stats: RolloutStats) -> RunningEpisode:
        self.policy.reset([episode.episode_id])
        spec = episode_spec(episode)
        t0 = time.perf_counter()
        try:
            obs = self.env.reset_env(slot, spec)
        except ENGINE_ERRORS as err:
            logger.warning(
                "episode %s: simulator reset failed (%s); scored from its start", episode.episode_id, err
            )
            record = new_record(episode, split, self.policy.name, spec.start.as_array())
            record.end_reason, record.error = "error", f"reset failed: {type(err).__name__}: {err}"
            blank = Observation(rgb=NO_FRAME, pose=spec.start)
            return RunningEpisode(slot, episode, blank, record)
        stats.sim_s += time.perf_counter() - t0
        running = RunningEpisode(
            slot, episode, obs, new_record(episode, split, self.policy.name, obs.pose.as_array())
        )
        for hook in self.hooks:
            hook.on_episode_start(running)
        return running

    def _observation(self, running: RunningEpisode) -> dict:
        obs = {
            OBS_EPISODE_ID: running.episode.episode_id,
            C.OBS_INSTRUCTION: running.episode.instruction,
            C.OBS_RGB: running.obs.rgb,
            C.OBS_POSE: running.obs.pose.as_array(),
            OBS_STEP: len(running.record.actions),
        }
        if self.policy.features.target_box:  # privileged: the simulator's box of the target landmark
            obs[OBS_TARGET_BOX] = running.target_box()
        for hook in self.hooks:
            obs.update(hook.observation_fields(running))
        return obs

    def _act(self, asked: list[RunningEpisode], stats: RolloutStats) -> list[int]:
        """The policy's actions for `asked` (one batched call), their step details stored on each."""
        observations = [self._observation(running) for running in asked]
        t0 = time.perf_counter()
        actions = check_actions(self.policy.name, self.policy.act(observations), len(observations))
        details = step_details(self.policy, [o[OBS_EPISODE_ID] for o in observations])
        stats.policy_s += time.perf_counter() - t0
        stats.policy_calls += 1
        for running, detail in zip(asked, details):
            running.detail = detail
        return actions

    def _step(self, active: list[RunningEpisode], stats: RolloutStats) -> list[int]:
        """One lockstep step over the `active` episodes; returns the slots whose episode just ended."""
        asked = [r for r in active if all(hook.asks_policy(r) for hook in self.hooks)]
        proposed = dict(zip((r.slot for r in asked), self._act(asked, stats))) if asked else {}
        stats.steps += len(active)
        moves: list[int | None] = [None] * self.env.num_envs
        chosen = []
        for running in active:
            if running.slot not in proposed:
                running.detail = {}
            action = proposed.get(running.slot)
            for hook in self.hooks:
                action = hook.choose_action(running, action)
            chosen.append(action)
            running.record.boxes.append(box_list(running.detail.get("box")))
            running.record.keyframes.append(running.detail.get("keyframes"))
            for hook in self.hooks:
                hook.on_step(running, action)
            if action != C.ACTION_STOP:
                moves[running.slot] = action
        t0 = time.perf_counter()
        new_obs, infos = self.env.step(moves) if any(m is not None for m in moves) else ([], [])
        stats.sim_s += time.perf_counter() - t0

        ended = []
        for running, action in zip(active, chosen):
            record = running.record
            record.actions.append(action)
            if action == C.ACTION_STOP:
                record.poses.append(list(record.poses[-1]))
                record.stopped, record.end_reason = True, "stop"
                ended.append(running.slot)
                continue
            obs, info = new_obs[running.slot], infos[running.slot]
            running.obs = obs
            record.poses.append([float(v) for v in obs.pose.as_array()])
            if info.collided:
                record.collision_steps.append(len(record.actions) - 1)
            if info.done:
                record.error = info.extra.get(ERROR_KEY)
                record.end_reason = "error" if record.error else "collision"
                ended.append(running.slot)
            elif len(record.actions) >= self.max_steps:
                ended.append(running.slot)
        return ended


def groups(episodes: list[Episode], size: int) -> list[list[Episode]]:
    """The lockstep groups `LockstepRunner.run` forms with `whole_groups`: consecutive runs of `size` episodes."""
    return [episodes[i : i + size] for i in range(0, len(episodes), size)]
