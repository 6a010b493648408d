"""Dataset episodes as evaluation tasks: simulator start specs, reference paths and the oracle's actions.

The oracle replays an episode's ground-truth actions when they reproduce its recorded positions through
`sim/dynamics.py` (always the case for generated data); otherwise it follows the recorded poses
(see `oracle_replays_exactly` and docs/EVAL.md).
"""

from __future__ import annotations

import numpy as np

from openfly_agent import constants as C
from openfly_agent.data.schema import Episode
from openfly_agent.sim.base import EpisodeSpec
from openfly_agent.sim.dynamics import rollout_array
from openfly_agent.utils.geometry import Pose

# Take-off / landing phases are executed as the climb / descent they are (constants.py).
_PHASE_TO_MODEL_ACTION = {C.ACTION_TAKEOFF: C.ACTION_ASCEND, C.ACTION_LANDING: C.ACTION_DESCEND}
REPLAY_TOLERANCE_M = 1e-3


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


def _recorded_moves(episode: Episode) -> list[int]:
    """The actions whose result is recorded (all but the last frame's), phases as model actions."""
    return [_PHASE_TO_MODEL_ACTION.get(int(a), int(a)) for a in episode.actions[:-1]]


def oracle_actions(episode: Episode) -> list[int]:
    """The ground-truth motion as model actions, then STOP on the last recorded position.

    The actions of frames 0..T-2 are executed (their results are the recorded positions 1..T-1), with STOPs
    dropped and take-off / landing as ascend / descend; the last frame's action has no recorded result (it
    is STOP in generated data), so the oracle stops on the last recorded pose (the official goal).
    """
    return [a for a in _recorded_moves(episode) if a != C.ACTION_STOP] + [C.ACTION_STOP]


def oracle_replays_exactly(episode: Episode, tolerance_m: float = REPLAY_TOLERANCE_M) -> bool:
    """Whether `positions[t + 1] == apply_action(pose[t], actions[t])` for every recorded frame.

    Checked by executing the recorded actions from the start through `sim/dynamics.py` (positions within
    `tolerance_m`). True for generated data; false for most released episodes (label quirks, docs/OFFICIAL_OPENFLY.md 1.2).
    """
    if len(episode) == 0:
        return False
    visited = rollout_array(start_pose(episode), _recorded_moves(episode))[:, :3]  # (T, 3)
    recorded = np.asarray(episode.positions, dtype=np.float64)  # (T, 3)
    return bool(np.linalg.norm(visited - recorded, axis=1).max() <= tolerance_m)
