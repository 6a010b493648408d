"""A dataset episode as a closed-loop task: the simulator's start spec, the goal, the target and the reference path."""

from __future__ import annotations

import numpy as np

from openfly_agent.data.schema import Episode
from openfly_agent.sim.base import EpisodeSpec
from openfly_agent.utils.geometry import Pose


def start_pose(episode: Episode) -> Pose:
    """The pose the episode starts from: `positions[0]`, `yaws[0]`."""
    x, y, z = (float(v) for v in episode.positions[0])
    return Pose(x, y, z, float(episode.yaws[0]))


def target_landmark(episode: Episode) -> str | None:
    """The final target landmark (the last of `landmark_ids`), or None when the data has none."""
    return episode.landmark_ids[-1] if episode.landmark_ids else None


def goal_of(episode: Episode) -> np.ndarray:
    """(3,) goal in metres: `episode.goal`, which defaults to the last position (official evaluation)."""
    goal = episode.goal if episode.goal is not None else episode.positions[-1]
    return np.asarray(goal, dtype=np.float64).reshape(3)


def episode_spec(episode: Episode) -> EpisodeSpec:
    """What the simulator needs to start `episode`: scene, start pose, camera pitch, goal and landmark."""
    return EpisodeSpec(
        episode_id=episode.episode_id,
        scene_id=episode.scene_id,
        start=start_pose(episode),
        goal=goal_of(episode),
        pitch_deg=float(episode.pitch_deg),
        landmark_id=target_landmark(episode),
    )


def reference_path(episode: Episode) -> np.ndarray:
    """(T, 3) the ground-truth positions, start first (what nDTW and the `standard` SPL compare against)."""
    return np.asarray(episode.positions, dtype=np.float64).reshape(-1, 3).copy()
