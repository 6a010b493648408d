"""What evaluation adds to the closed loop (rollout/runner.py): GIF frames of chosen episodes, and the oracle's
record of an episode whose actions do not replay."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from openfly_agent import constants as C
from openfly_agent.data.schema import Episode
from openfly_agent.rollout.episodes import start_pose
from openfly_agent.rollout.record import EpisodeRecord
from openfly_agent.rollout.runner import RolloutHook, RunningEpisode, box_list, new_record


@dataclass
class FrameLog:
    """Egocentric frames of one episode for a GIF: RGB, predicted and ground-truth target box per frame."""

    frames: list[np.ndarray] = field(default_factory=list)  # (H, W, 3) uint8 each
    predicted_boxes: list[list[float] | None] = field(default_factory=list)
    target_boxes: list[list[float] | None] = field(default_factory=list)


class FrameRecorder(RolloutHook):
    """Keeps the frames of the episodes in `episode_ids` and hands each finished one to `on_frames`."""

    def __init__(self, episode_ids: set[str], on_frames: Callable[[EpisodeRecord, FrameLog], None]):
        self.episode_ids, self.on_frames = set(episode_ids), on_frames

    def on_episode_start(self, running: RunningEpisode) -> None:
        if running.episode.episode_id in self.episode_ids:
            running.state[FrameLog] = FrameLog()

    def on_step(self, running: RunningEpisode, action: int) -> None:
        frames = running.state.get(FrameLog)
        if frames is not None:
            frames.frames.append(np.array(running.obs.rgb, copy=True))
            frames.predicted_boxes.append(box_list(running.detail.get("box")))
            frames.target_boxes.append(running.target_box())

    def on_episode_end(self, running: RunningEpisode) -> None:
        frames = running.state.get(FrameLog)
        if frames is not None:
            self.on_frames(running.record, frames)


def teleport_record(episode: Episode, split: str, policy_name: str, max_steps: int) -> EpisodeRecord:
    """The oracle's record for an episode whose actions do not replay: it moves along the recorded poses.

    Poses are the recorded ones, cut after `max_steps` moves, then STOP (when within the step budget); the
    actions are the recorded labels of those moves, for reference only. No simulator is stepped.
    """
    poses = episode.poses[: max_steps + 1]  # (M + 1, 4)
    moves = len(poses) - 1
    stopped = len(episode) <= max_steps  # T - 1 moves, then the STOP: T actions in the budget
    record = new_record(episode, split, policy_name, start_pose(episode).as_array())
    record.poses = poses.tolist() + ([poses[-1].tolist()] if stopped else [])
    record.actions = [int(a) for a in episode.actions[:moves]] + ([C.ACTION_STOP] if stopped else [])
    record.stopped, record.end_reason = stopped, "teleport" if stopped else "max_steps"
    return record
