"""Where the current leg's goal lies at every step of an expert episode: the auxiliary target of
`action_head.leg_goal_weight` (and the label probes' leg-goal features, bench/analysis/label_predictability.py).

On a chained route (`Episode.leg_goals`, one goal per target landmark) a leg ends at the step nearest its goal
after the previous leg's end (the A* path reaches each leg's goal within its tolerance there); that step is the
next leg's first decision, as the toolchain's leg boxes count it. A route of one leg, or an episode without
`leg_goals`, has its last position as the goal of every step.
"""

from __future__ import annotations

import numpy as np

from openfly_agent.data.schema import Episode

LEG_GOAL_DISTANCE_SCALE_M = 50.0  # the target's distance is divided by this to keep it near unit scale


def leg_goal_per_step(episode: Episode) -> np.ndarray:
    """(T, 3) float64 the goal of the leg each of the T = len(actions) steps belongs to."""
    positions = np.asarray(episode.positions, dtype=np.float64)[: len(episode.actions)]  # (T, 3)
    if episode.leg_goals is None or len(episode.leg_goals) < 2:
        return np.repeat(positions[-1:], len(positions), axis=0)
    goals = np.asarray(episode.leg_goals, dtype=np.float64)  # (K, 3)
    ends, start = [], 0
    for goal in goals[:-1]:
        start += int(np.argmin(np.linalg.norm(positions[start:] - goal, axis=1)))
        ends.append(start)
    legs = np.searchsorted(np.asarray(ends), np.arange(len(positions)), side="right")  # (T,) 0 .. K-1
    return goals[legs]


def wrap_angle(angle: np.ndarray) -> np.ndarray:
    """Radians wrapped to [-pi, pi)."""
    return (np.asarray(angle) + np.pi) % (2.0 * np.pi) - np.pi


def distance_and_bearing(
    positions: np.ndarray, yaws: np.ndarray, goals: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """(T,) horizontal distance from (T, 3) positions to (T, 3) goals over LEG_GOAL_DISTANCE_SCALE_M, and each
    goal's bearing off the (T,) heading in radians, counter-clockwise positive (a goal on the left is > 0)."""
    delta = goals[:, :2] - positions[:, :2]  # (T, 2)
    bearing = wrap_angle(np.arctan2(delta[:, 1], delta[:, 0]) - yaws)
    return np.linalg.norm(delta, axis=1) / LEG_GOAL_DISTANCE_SCALE_M, bearing


def leg_goal_targets(episode: Episode) -> np.ndarray:
    """(T, 3) float32 per step: sin and cos of the current leg goal's bearing and its distance over 50 m.

    E.g. a goal 25 m to the drone's left: (1, 0, 0.5).
    """
    n = len(episode.actions)
    positions = np.asarray(episode.positions, dtype=np.float64)[:n]  # (T, 3)
    yaws = np.asarray(episode.yaws, dtype=np.float64)[:n]  # (T,)
    distance, bearing = distance_and_bearing(positions, yaws, leg_goal_per_step(episode))
    return np.stack([np.sin(bearing), np.cos(bearing), distance], axis=1).astype(np.float32)
