"""Collision checks of motion segments against an occupancy grid and the ground, and the collision policies.

A step collides when the straight segment from its start to its end position passes through an
occupied voxel or touches the ground (z <= ground_z). Policies: `end` (the drone stays where it was and
the episode ends), `count` (the motion happens, the collision is only flagged), `ignore` (no check,
as in the official OpenFly evaluation).
"""

from __future__ import annotations

import numpy as np

from openfly_agent.sim.dynamics import Motion
from openfly_agent.sim.occupancy import OccupancyGrid

COLLISION_POLICIES = ("end", "count", "ignore")


def check_policy(policy: str) -> str:
    """`policy` if valid, else a ValueError listing the choices."""
    if policy not in COLLISION_POLICIES:
        raise ValueError(f"collision policy must be one of {COLLISION_POLICIES}, got {policy!r}")
    return policy


def motion_collides(occupancy: OccupancyGrid, motion: Motion, ground_z: float | None = 0.0) -> bool:
    """True if the segment swept by `motion` hits an occupied voxel or the ground (STOP never collides)."""
    if motion.is_stop:
        return False
    return occupancy.segment_collides(motion.start.position, motion.end.position, ground_z=ground_z)


def segments_collide(
    occupancy: OccupancyGrid, starts: np.ndarray, ends: np.ndarray, ground_z: float | None = 0.0
) -> np.ndarray:
    """Vectorised check of many segments: (N, 3) starts and ends -> (N,) bool.

    Same sampling as `OccupancyGrid.segment_collides` (a quarter voxel), so both agree exactly.
    """
    starts, ends = np.atleast_2d(starts).astype(np.float64), np.atleast_2d(ends).astype(np.float64)
    if len(starts) == 0:
        return np.zeros(0, dtype=bool)
    lengths = np.linalg.norm(ends - starts, axis=1)  # (N,)
    counts = np.maximum(2, np.ceil(lengths / (0.25 * occupancy.voxel_size)).astype(np.int64) + 1)  # (N,)
    seg = np.repeat(np.arange(len(starts)), counts)  # (S,) segment of each sample
    first = np.concatenate([[0], np.cumsum(counts)[:-1]])
    t = (np.arange(len(seg)) - first[seg]) / (counts[seg] - 1)  # (S,) in [0, 1]
    samples = starts[seg] + t[:, None] * (ends[seg] - starts[seg])  # (S, 3)
    hit = occupancy.is_occupied(samples)
    if ground_z is not None:
        hit |= samples[:, 2] <= ground_z
    return np.bincount(seg, weights=hit, minlength=len(starts)) > 0
