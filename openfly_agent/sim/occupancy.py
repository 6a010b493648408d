"""Occupancy voxel grid: the structure collisions are checked against and A* plans in.

Built from a point cloud (real scenes, toolchain) or from the embedded city's buildings. Voxel (i, j, k)
covers [origin + (i, j, k) * voxel, origin + (i + 1, j + 1, k + 1) * voxel). Points outside the grid
count as occupied when `outside_occupied` is set (the official planner does this).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from openfly_agent.sim.scene import SceneBounds


@dataclass
class OccupancyGrid:
    origin: np.ndarray  # (3,) metres, corner of voxel (0, 0, 0)
    voxel_size: float  # metres
    occupied: np.ndarray  # (NX, NY, NZ) bool
    outside_occupied: bool = False

    @classmethod
    def empty(cls, bounds: SceneBounds, voxel_size: float, outside_occupied: bool = False) -> OccupancyGrid:
        shape = tuple(
            max(1, math.ceil((hi - lo) / voxel_size))
            for lo, hi in ((bounds.xmin, bounds.xmax), (bounds.ymin, bounds.ymax), (bounds.zmin, bounds.zmax))
        )
        origin = np.array([bounds.xmin, bounds.ymin, bounds.zmin], dtype=np.float64)
        return cls(origin, float(voxel_size), np.zeros(shape, dtype=bool), outside_occupied)

    @classmethod
    def from_points(
        cls, points: np.ndarray, bounds: SceneBounds, voxel_size: float, outside_occupied: bool = False
    ) -> OccupancyGrid:
        """Mark every voxel that holds at least one of `points` (N, 3); points outside `bounds` are ignored."""
        grid = cls.empty(bounds, voxel_size, outside_occupied)
        idx, inside = grid.index_of(np.asarray(points, dtype=np.float64))
        idx = idx[inside]
        grid.occupied[idx[:, 0], idx[:, 1], idx[:, 2]] = True
        return grid

    @property
    def shape(self) -> tuple[int, int, int]:
        return tuple(self.occupied.shape)

    @property
    def bounds(self) -> SceneBounds:
        hi = self.origin + np.array(self.shape) * self.voxel_size
        return SceneBounds(self.origin[0], hi[0], self.origin[1], hi[1], self.origin[2], hi[2])

    def index_of(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(N, 3) metres -> (N, 3) int voxel indices and (N,) bool `inside the grid`."""
        idx = np.floor((np.atleast_2d(points) - self.origin) / self.voxel_size).astype(np.int64)
        inside = np.all((idx >= 0) & (idx < np.array(self.shape)), axis=1)
        return idx, inside

    def mark_box(self, lo: np.ndarray, hi: np.ndarray) -> None:
        """Mark every voxel that intersects the axis-aligned box [lo, hi] (metres)."""
        a = np.floor((np.asarray(lo) - self.origin) / self.voxel_size).astype(np.int64)
        b = np.ceil((np.asarray(hi) - self.origin) / self.voxel_size).astype(np.int64)
        a = np.clip(a, 0, self.shape)
        b = np.clip(b, 0, self.shape)
        if np.all(b > a):
            self.occupied[a[0] : b[0], a[1] : b[1], a[2] : b[2]] = True

    def is_occupied(self, points: np.ndarray) -> np.ndarray:
        """(N, 3) metres -> (N,) bool."""
        idx, inside = self.index_of(points)
        out = np.full(len(idx), self.outside_occupied, dtype=bool)
        ii = idx[inside]
        out[inside] = self.occupied[ii[:, 0], ii[:, 1], ii[:, 2]]
        return out

    def dilate(self, radius_m: float) -> OccupancyGrid:
        """A copy with obstacles inflated by ceil(radius / voxel) voxels (a cube, as the official planner)."""
        r = int(math.ceil(radius_m / self.voxel_size))
        if r <= 0:
            return OccupancyGrid(
                self.origin.copy(), self.voxel_size, self.occupied.copy(), self.outside_occupied
            )
        occ = self.occupied
        for axis in range(3):  # separable max filter
            padded = np.pad(occ, [(r, r) if a == axis else (0, 0) for a in range(3)])
            acc = np.zeros_like(occ)
            n = occ.shape[axis]
            for shift in range(2 * r + 1):
                acc |= np.take(padded, np.arange(shift, shift + n), axis=axis)
            occ = acc
        return OccupancyGrid(self.origin.copy(), self.voxel_size, occ, self.outside_occupied)

    def segment_collides(self, start: np.ndarray, end: np.ndarray, ground_z: float | None = None) -> bool:
        """True if the straight segment start -> end (metres) passes through an occupied voxel or below ground.

        Samples the segment at a quarter voxel, so no voxel the segment crosses is skipped.
        """
        start, end = np.asarray(start, dtype=np.float64), np.asarray(end, dtype=np.float64)
        length = float(np.linalg.norm(end - start))
        n = max(2, int(math.ceil(length / (0.25 * self.voxel_size))) + 1)
        samples = start + np.linspace(0.0, 1.0, n)[:, None] * (end - start)  # (n, 3)
        if ground_z is not None and np.any(samples[:, 2] <= ground_z):
            return True
        return bool(self.is_occupied(samples).any())

    def bev(self, min_z: float | None = None) -> np.ndarray:
        """(NX, NY) bool: column occupied anywhere above `min_z` (metres)."""
        occ = self.occupied
        if min_z is not None:
            k0 = int(np.clip(math.floor((min_z - self.origin[2]) / self.voxel_size), 0, self.shape[2]))
            occ = occ[:, :, k0:]
        return occ.any(axis=2)
