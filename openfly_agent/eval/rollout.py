"""The closed-loop runner: episodes in lockstep groups, one batched policy call per step.

Episodes run in consecutive groups of `num_slots` (the batch size): a group starts together, and at every
step the policy gets the observations of the group's running episodes at once, the environment executes
the actions, and an episode that stops, hits the step cap or meets an engine error is written out
(`on_finish`); the next group starts when the last episode of this one has ended. Episodes never share
state, so results do not depend on the batch size beyond float rounding, and because an episode's batch
companions at every step depend only on the episode list and the batch size, a group recomputed after a
kill gives bit-identical results (eval/run.py resumes by whole groups; docs/EVAL.md).
"""

from __future__ import annotations

import logging
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from tqdm.auto import tqdm

from openfly_agent import constants as C
from openfly_agent.data.schema import Episode
from openfly_agent.eval.episodes import episode_spec, goal_of, reference_path, target_landmark
from openfly_agent.eval.policy import OBS_EPISODE_ID, OBS_STEP, Policy, check_actions, step_details
from openfly_agent.eval.records import EpisodeRecord
from openfly_agent.eval.slots import ENGINE_ERRORS, ERROR_KEY, SlotEnv
from openfly_agent.sim.base import Observation

logger = logging.getLogger(__name__)


@dataclass
class RolloutStats:
    """Counters of one `run_episodes` call; times in seconds (wall clock)."""

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
class FrameLog:
    """Egocentric frames of one episode for a GIF: RGB, predicted and ground-truth target box per frame."""

    frames: list[np.ndarray] = field(default_factory=list)  # (H, W, 3) uint8 each
    predicted_boxes: list[list[float] | None] = field(default_factory=list)
    target_boxes: list[list[float] | None] = field(default_factory=list)


@dataclass
class _Running:
    episode: Episode
    obs: Observation
    record: EpisodeRecord
    frames: FrameLog | None = None


def _new_record(episode: Episode, split: str, policy_name: str, obs: Observation) -> EpisodeRecord:
    return EpisodeRecord(
        split=split,
        episode_id=episode.episode_id,
        scene_id=episode.scene_id,
        policy=policy_name,
        instruction=episode.instruction,
        goal=[float(v) for v in goal_of(episode)],
        reference_path=reference_path(episode).tolist(),
        actions=[],
        poses=[[float(v) for v in obs.pose.as_array()]],
        stopped=False,
        end_reason="max_steps",
    )


def _policy_obs(running: _Running) -> dict:
    return {
        OBS_EPISODE_ID: running.episode.episode_id,
        C.OBS_INSTRUCTION: running.episode.instruction,
        C.OBS_RGB: running.obs.rgb,
        C.OBS_POSE: running.obs.pose.as_array(),
        OBS_STEP: len(running.record.actions),
    }


def _box_list(box) -> list[float] | None:
    return None if box is None else [float(v) for v in np.asarray(box, dtype=np.float64).reshape(4)]


class LockstepRunner:
    """Runs episodes of one split through `env` with `policy`.

    Args:
        policy: any `Policy`.
        env: the slot environment; its `num_slots` is the lockstep batch size.
        max_steps: actions per episode at most (the official evaluation: 100).
        gif_episode_ids: episodes whose frames are kept and handed to `on_frames`.
        show_progress: draw a tqdm bar.
    """

    def __init__(
        self,
        policy: Policy,
        env: SlotEnv,
        max_steps: int = C.MAX_EPISODE_STEPS,
        gif_episode_ids: set[str] | None = None,
        show_progress: bool = True,
    ):
        if max_steps < 1:
            raise ValueError(f"max_steps must be >= 1, got {max_steps}")
        self.policy, self.env, self.max_steps = policy, env, int(max_steps)
        self.gif_episode_ids = set(gif_episode_ids or ())
        self.show_progress = show_progress
        self.stats = RolloutStats()

    def run(
        self,
        episodes: list[Episode],
        split: str,
        on_finish: Callable[[EpisodeRecord], None],
        on_frames: Callable[[EpisodeRecord, FrameLog], None] | None = None,
    ) -> RolloutStats:
        """Run every episode of `episodes` to its end, calling `on_finish(record)` as each one finishes.

        Episodes run in groups of `num_slots`, in list order (`groups`); a slot whose episode ended waits for
        the rest of its group, so no episode's batch depends on which other episodes were run before.
        """
        stats = RolloutStats()
        queue = deque(episodes)
        slots: list[_Running | None] = [None] * self.env.num_slots
        bar = tqdm(
            total=len(episodes),
            desc=f"{self.policy.name}/{split}",
            disable=not self.show_progress,
            leave=False,
        )

        def finish(slot: int) -> None:
            running = slots[slot]
            slots[slot] = None
            self.policy.reset([running.episode.episode_id])
            on_finish(running.record)
            if running.frames is not None and on_frames is not None:
                on_frames(running.record, running.frames)
            stats.episodes += 1
            bar.update(1)

        try:
            while True:
                if all(running is None for running in slots):  # the previous group is over: start the next
                    for slot in range(self.env.num_slots):
                        if queue:
                            slots[slot] = self._start(slot, queue.popleft(), split, stats)
                            if slots[slot].record.end_reason == "error":
                                finish(slot)
                active = [i for i, running in enumerate(slots) if running is not None]
                if not active:
                    if queue:
                        continue
                    break
                for slot in self._step(slots, active, stats):
                    finish(slot)
        finally:
            bar.close()
        self.stats.add(stats)
        return stats

    def _start(self, slot: int, episode: Episode, split: str, stats: RolloutStats) -> _Running:
        self.policy.reset([episode.episode_id])
        t0 = time.perf_counter()
        try:
            obs = self.env.reset_slot(slot, episode_spec(episode))
        except ENGINE_ERRORS as err:
            logger.warning(
                "episode %s: simulator reset failed (%s); scored from its start", episode.episode_id, err
            )
            return _failed_start(episode, split, self.policy.name, err)
        stats.sim_s += time.perf_counter() - t0
        running = _Running(episode, obs, _new_record(episode, split, self.policy.name, obs))
        if episode.episode_id in self.gif_episode_ids:
            running.frames = FrameLog()
        return running

    def _step(self, slots: list[_Running | None], active: list[int], stats: RolloutStats) -> list[int]:
        """One lockstep step over the `active` slots; returns the slots whose episode just ended."""
        observations = [_policy_obs(slots[i]) for i in active]
        episode_ids = [o[OBS_EPISODE_ID] for o in observations]
        t0 = time.perf_counter()
        actions = check_actions(self.policy.name, self.policy.act(observations), len(observations))
        details = step_details(self.policy, episode_ids)
        stats.policy_s += time.perf_counter() - t0
        stats.policy_calls += 1
        stats.steps += len(active)

        moves: list[int | None] = [None] * self.env.num_slots
        for slot, action, detail in zip(active, actions, details):
            running = slots[slot]
            running.record.boxes.append(_box_list(detail.get("box")))
            running.record.keyframes.append(detail.get("keyframes"))
            if running.frames is not None:
                _log_frame(running, detail)
            if action != C.ACTION_STOP:
                moves[slot] = action
        t0 = time.perf_counter()
        new_obs, infos = self.env.step(moves) if any(m is not None for m in moves) else ([], [])
        stats.sim_s += time.perf_counter() - t0

        ended = []
        for slot, action in zip(active, actions):
            running = slots[slot]
            record = running.record
            record.actions.append(action)
            if action == C.ACTION_STOP:
                record.poses.append(list(record.poses[-1]))
                record.stopped, record.end_reason = True, "stop"
                ended.append(slot)
                continue
            obs, info = new_obs[slot], infos[slot]
            running.obs = obs
            record.poses.append([float(v) for v in obs.pose.as_array()])
            if info.collided:
                record.collision_steps.append(len(record.actions) - 1)
            if info.done:
                record.error = info.extra.get(ERROR_KEY)
                record.end_reason = "error" if record.error else "collision"
                ended.append(slot)
            elif len(record.actions) >= self.max_steps:
                ended.append(slot)
        return ended


def groups(episodes: list[Episode], size: int) -> list[list[Episode]]:
    """The lockstep groups `LockstepRunner.run` forms: consecutive runs of `size` episodes, in list order."""
    return [episodes[i : i + size] for i in range(0, len(episodes), size)]


def _log_frame(running: _Running, detail: dict) -> None:
    boxes = running.obs.boxes or {}
    landmark = target_landmark(running.episode)
    running.frames.frames.append(np.array(running.obs.rgb, copy=True))
    running.frames.predicted_boxes.append(_box_list(detail.get("box")))
    running.frames.target_boxes.append(_box_list(boxes.get(landmark)) if landmark else None)


def _failed_start(episode: Episode, split: str, policy_name: str, err: Exception) -> _Running:
    start = episode_spec(episode).start
    obs = Observation(rgb=np.zeros((1, 1, 3), dtype=np.uint8), pose=start)
    record = _new_record(episode, split, policy_name, obs)
    record.end_reason, record.error = "error", f"reset failed: {type(err).__name__}: {err}"
    return _Running(episode, obs, record)


def teleport_record(episode: Episode, split: str, policy_name: str, max_steps: int) -> EpisodeRecord:
    """The oracle's record for an episode whose actions do not replay: it moves along the recorded poses.

    Poses are the recorded ones, cut after `max_steps` moves, then STOP (when within the step budget); the
    actions are the recorded labels of those moves, for reference only. No simulator is stepped.
    """
    poses = episode.poses[: max_steps + 1]  # (M + 1, 4)
    moves = len(poses) - 1
    stopped = len(episode) <= max_steps  # T - 1 moves, then the STOP: T actions in the budget
    obs = Observation(rgb=np.zeros((1, 1, 3), dtype=np.uint8), pose=episode_spec(episode).start)
    record = _new_record(episode, split, policy_name, obs)
    record.poses = poses.tolist() + ([poses[-1].tolist()] if stopped else [])
    record.actions = [int(a) for a in episode.actions[:moves]] + ([C.ACTION_STOP] if stopped else [])
    record.stopped, record.end_reason = stopped, "teleport" if stopped else "max_steps"
    return record
