"""The oracle's actions of a dataset episode (its start spec, goal and reference path: rollout/episodes.py).

The oracle replays an episode's ground-truth actions when they reproduce its recorded positions through
`sim/dynamics.py` (always the case for generated data); otherwise it follows the recorded poses
(see `oracle_replays_exactly` and docs/EVAL.md).
"""

from __future__ import annotations

import numpy as np

from openfly_agent import constants as C
from openfly_agent.data.schema import Episode
from openfly_agent.rollout.episodes import start_pose
from openfly_agent.sim.dynamics import rollout_array

# Take-off / landing phases are executed as the climb / descent they are (constants.py).
_PHASE_TO_MODEL_ACTION = {C.ACTION_TAKEOFF: C.ACTION_ASCEND, C.ACTION_LANDING: C.ACTION_DESCEND}
REPLAY_TOLERANCE_M = 1e-3


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
