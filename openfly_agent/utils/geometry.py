"""Poses and angles in the world frame of docs/CONVENTIONS.md (right-handed, metres, x east, y north, z up)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


def wrap_yaw(yaw: float) -> float:
    """Wrap an angle in radians to (-pi, pi]."""
    wrapped = math.fmod(yaw + math.pi, 2.0 * math.pi)
    if wrapped <= 0.0:
        wrapped += 2.0 * math.pi
    return wrapped - math.pi


@dataclass(frozen=True)
class Pose:
    """A drone pose: position in metres and yaw in radians, CCW from +x (a left turn increases yaw)."""

    x: float
    y: float
    z: float
    yaw: float

    def as_array(self) -> np.ndarray:
        return np.array([self.x, self.y, self.z, self.yaw], dtype=np.float64)

    @property
    def position(self) -> np.ndarray:
        return np.array([self.x, self.y, self.z], dtype=np.float64)

    def heading(self) -> np.ndarray:
        """Unit vector (2,) of the heading in the x-y plane."""
        return np.array([math.cos(self.yaw), math.sin(self.yaw)], dtype=np.float64)

    def distance_to(self, other: Pose) -> float:
        return float(np.linalg.norm(self.position - other.position))


def path_length(positions: np.ndarray) -> float:
    """Sum of Euclidean segment lengths of a (T, 3) polyline."""
    positions = np.asarray(positions, dtype=np.float64)
    if len(positions) < 2:
        return 0.0
    return float(np.linalg.norm(np.diff(positions, axis=0), axis=1).sum())
