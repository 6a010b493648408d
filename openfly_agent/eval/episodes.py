"""Dataset episodes as evaluation tasks: simulator start specs, reference paths and the oracle's actions.

The oracle replays an episode's ground-truth actions when they reproduce its poses through
`sim/dynamics.py` (always the case for generated data); otherwise it follows the ground-truth poses
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
    """(G, 3) ground-truth positions, start first, ending at the goal when the goal lies beyond them."""
    path = np.asarray(episode.positions, dtype=np.float64).reshape(-1, 3)
    goal = goal_of(episode)
    if len(path) == 0 or np.linalg.norm(path[-1] - goal) > REPLAY_TOLERANCE_M:
        path = np.concatenate([path, goal[None]], axis=0)
    return path


def oracle_actions(episode: Episode) -> list[int]:
    """The ground-truth motion as model actions: STOPs removed, take-off / landing as 4 / 5, then STOP.

    Released annotations put the landing descent (-2) after STOP; moving STOP to the end makes the oracle
    finish on the landed point, which is the goal of the official evaluation.
    """
    moves = [_PHASE_TO_MODEL_ACTION.get(int(a), int(a)) for a in episode.actions if int(a) != C.ACTION_STOP]
    return [*moves, C.ACTION_STOP]


def oracle_replays_exactly(episode: Episode, tolerance_m: float = REPLAY_TOLERANCE_M) -> bool:
    """Whether the actions, executed from the episode start, visit its recorded positions and end at the goal.

    Checks `positions[t + 1] == apply_action(pose[t], actions[t])` for every recorded frame (position only,
    within `tolerance_m`) and that the last motion ends within `tolerance_m` of the goal.
    """
    if len(episode) == 0:
        return False
    actions = [_PHASE_TO_MODEL_ACTION.get(int(a), int(a)) for a in episode.actions]
    visited = rollout_array(start_pose(episode), actions)[:, :3]  # (T + 1, 3)
    recorded = np.asarray(episode.positions, dtype=np.float64)  # (T, 3)
    along = np.linalg.norm(visited[: len(recorded)] - recorded, axis=1).max()
    at_goal = np.linalg.norm(visited[-1] - goal_of(episode))
    return bool(along <= tolerance_m and at_goal <= tolerance_m)
