"""Label handling of released OpenFly episodes: action-sequence checks, the -1 / -2 phases, merged forwards.

Reference: docs/OFFICIAL_OPENFLY.md 1.2 (label/frame quirk) and 7.4 (take-off / landing order). The options
are described for users in data_cards/openfly_released.md.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from openfly_agent import constants as C
from openfly_agent.data.config import ReaderOptions
from openfly_agent.data.schema import Episode, SchemaError

FORWARD_LABELS = {1: C.ACTION_FORWARD, 2: C.ACTION_FORWARD_6, 3: C.ACTION_FORWARD_9}  # primitives -> id
FORWARD_IDS = frozenset(FORWARD_LABELS.values())
# A kept-frame displacement counts as a pure forward move of k * 3 m when it is within these tolerances.
FORWARD_DISTANCE_TOL_M = 0.5
FORWARD_OFFAXIS_TOL_M = 0.5  # lateral and vertical
FORWARD_YAW_TOL_RAD = math.radians(1.0)


def check_action_sequence(actions: np.ndarray, file: str, record: int | str) -> None:
    """Raise `SchemaError` unless `actions` is `(-1)* nav 0 (-2)*` with ids in ALL_ACTION_IDS.

    That is: every id known, exactly one STOP, take-off climbs only as a leading run, landing descents
    only after the STOP, and nothing else after the STOP.
    """
    actions = np.asarray(actions)
    unknown = [int(a) for a in actions if int(a) not in C.ACTION_NAMES]
    if unknown:
        raise SchemaError(file, record, "action", f"unknown action id(s) {sorted(set(unknown))}")
    stops = np.flatnonzero(actions == C.ACTION_STOP)
    if len(stops) != 1:
        raise SchemaError(file, record, "action", f"expected exactly one STOP (0), found {len(stops)}")
    stop = int(stops[0])
    if np.any(actions[stop + 1 :] != C.ACTION_LANDING):
        raise SchemaError(file, record, "action", f"only landing (-2) may follow the STOP at frame {stop}")
    if np.any(actions[:stop] == C.ACTION_LANDING):
        raise SchemaError(file, record, "action", "landing (-2) before the STOP")
    n_takeoff = _leading_run(actions, C.ACTION_TAKEOFF)
    if np.any(actions[n_takeoff:] == C.ACTION_TAKEOFF):
        raise SchemaError(file, record, "action", "take-off (-1) after the navigation segment started")


def _leading_run(actions: np.ndarray, value: int) -> int:
    """Length of the run of `value` at the start of `actions`."""
    not_value = np.flatnonzero(actions != value)
    return int(not_value[0]) if len(not_value) else len(actions)


def take_frames(episode: Episode, keep: np.ndarray) -> Episode:
    """A copy of `episode` holding only the frames `keep` (indices, increasing); goal unchanged."""
    keep = np.asarray(keep, dtype=np.int64)
    boxes = None if episode.boxes is None else episode.boxes[keep]
    visible = None if episode.box_visible is None else episode.box_visible[keep]
    return dataclasses.replace(
        episode,
        actions=episode.actions[keep],
        positions=episode.positions[keep],
        yaws=episode.yaws[keep],
        frame_ids=[episode.frame_ids[i] for i in keep],
        boxes=boxes,
        box_visible=visible,
        goal=None if episode.goal is None else episode.goal.copy(),
    )


def apply_takeoff_landing(episode: Episode, mode: str) -> Episode:
    """Handle the -1 / -2 phases as `ReaderOptions.takeoff_landing` describes (expects a checked sequence)."""
    actions = episode.actions
    if mode == "keep" or not np.any(actions < 0):
        return episode
    stop = int(np.flatnonzero(actions == C.ACTION_STOP)[0])
    if mode == "trim":
        start = _leading_run(actions, C.ACTION_TAKEOFF)
        trimmed = take_frames(episode, np.arange(start, stop + 1))
        trimmed.goal = trimmed.positions[-1].copy()  # the STOP pose: the landing is gone
        return trimmed
    if mode == "map":
        mapped = actions.copy()
        mapped[mapped == C.ACTION_TAKEOFF] = C.ACTION_ASCEND
        # Released: STOP at frame s, then -2 on frames s+1..T-1, each already 3 m lower (the label sits on
        # the frame where its descent ends). Mapped: descend on s..T-2 (where each descent starts), STOP last.
        mapped[stop:-1] = C.ACTION_DESCEND
        mapped[-1] = C.ACTION_STOP
        return dataclasses.replace(episode, actions=mapped)
    raise ValueError(f"takeoff_landing={mode!r}: choose keep, map or trim")


def forward_primitives(start: np.ndarray, end: np.ndarray, yaw_start: float, yaw_end: float) -> int | None:
    """Number k in {1, 2, 3} of 3 m forward primitives that move `start` to `end`, or None if not a pure move.

    Pure = the heading does not change, no vertical or sideways offset, and the distance along the
    heading is k * 3 m, all within the FORWARD_* tolerances.
    """
    if abs(math.remainder(yaw_end - yaw_start, 2.0 * math.pi)) > FORWARD_YAW_TOL_RAD:
        return None
    delta = np.asarray(end, dtype=np.float64) - np.asarray(start, dtype=np.float64)  # (3,)
    heading = np.array([math.cos(yaw_start), math.sin(yaw_start)])
    along = float(delta[:2] @ heading)
    sideways = float(delta[0] * -heading[1] + delta[1] * heading[0])
    if abs(sideways) > FORWARD_OFFAXIS_TOL_M or abs(delta[2]) > FORWARD_OFFAXIS_TOL_M:
        return None
    k = round(along / C.STEP_METERS)
    if k not in FORWARD_LABELS or abs(along - k * C.STEP_METERS) > FORWARD_DISTANCE_TOL_M:
        return None
    return k


def move_merged_forward_to_start(episode: Episode) -> tuple[Episode, int, int]:
    """Relabel forward frames (1 / 8 / 9) by the displacement to the next kept frame.

    Released labels sit on the last raw frame of a merged block: in eval_test #0 the kept frames
    `_2, _5, ..., _20` all carry 9 while frame `_20` is only 3 m before the turn frame `_21`. After this
    call frames `_2.._17` keep 9 (9 m to the next kept frame each) and `_20` becomes 1 (3 m): every
    forward label then describes the motion that starts at its own frame. A forward frame whose next
    displacement is not a pure 3 / 6 / 9 m forward move (e.g. a climb or a turn follows) keeps its label;
    turn, vertical and STOP frames are never changed, and the last frame is left as it is.

    Returns:
        (episode with new actions, number of labels changed, number of forward frames left unresolved).
    """
    actions = episode.actions.copy()
    changed = unresolved = 0
    for t in range(len(actions) - 1):
        if int(actions[t]) not in FORWARD_IDS:
            continue
        k = forward_primitives(
            episode.positions[t], episode.positions[t + 1], episode.yaws[t], episode.yaws[t + 1]
        )
        if k is None:
            unresolved += 1
        elif FORWARD_LABELS[k] != actions[t]:
            actions[t] = FORWARD_LABELS[k]
            changed += 1
    return dataclasses.replace(episode, actions=actions), changed, unresolved


def apply_reader_options(episode: Episode, options: ReaderOptions, file: str, record: int | str) -> Episode:
    """Check the action sequence, then apply the -1 / -2 and merged-forward options (in that order)."""
    check_action_sequence(episode.actions, file, record)
    episode = apply_takeoff_landing(episode, options.takeoff_landing)
    if options.merged_forward_position == "start":
        episode, _, _ = move_merged_forward_to_start(episode)
    return episode
