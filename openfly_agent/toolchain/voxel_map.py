"""Point cloud -> the planner's maps: a 3-D voxel grid (raw and dilated) and a BEV occupancy / height map.

Follows the official `traj_gen` maps (docs/OFFICIAL_OPENFLY.md 7.4): bounds with zmin = elevation, voxel width,
obstacles inflated by ceil(DilateRadius / VoxelWidth) voxels, outside the bounds = occupied, and a
single-layer BEV map of the points above elevation + min_height_thresh, dilated likewise.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from openfly_agent.sim.occupancy import OccupancyGrid
from openfly_agent.sim.scene import SceneBounds
from openfly_agent.toolchain.config import MapConfig


@dataclass
class PlanningMap:
    """Everything route sampling and A* look up. BEV arrays share the x-y voxels of `grid`."""

    grid: OccupancyGrid  # raw occupancy from the points, outside = occupied
    dilated: OccupancyGrid  # `grid` inflated by the dilate radius: where the drone may not be
    bev: np.ndarray  # (NX, NY) bool: a point above elevation + thresh in this column
    bev_dilated: np.ndarray  # (NX, NY) bool: `bev` inflated by the dilate radius
    height: np.ndarray  # (NX, NY) float: highest point z in the column, -inf where none
    elevation: float  # ground height (map_elevation)
    min_flight_z: float  # elevation + min_height_thresh: lowest z the planner flies at

    @property
    def voxel_size(self) -> float:
        return self.grid.voxel_size

    @property
    def bounds(self) -> SceneBounds:
        return self.grid.bounds

    def column_of(self, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(N, 2) metres -> (N, 2) int BEV cell indices and (N,) bool `inside the map`."""
        xy = np.atleast_2d(np.asarray(xy, dtype=np.float64))[:, :2]
        idx = np.floor((xy - self.grid.origin[:2]) / self.voxel_size).astype(np.int64)
        inside = np.all((idx >= 0) & (idx < np.array(self.bev.shape)), axis=1)
        return idx, inside

    def bev_blocked(self, xy: np.ndarray, dilated: bool = True) -> np.ndarray:
        """(N, 2) metres -> (N,) bool: over an obstacle footprint (or outside the map)."""
        idx, inside = self.column_of(xy)
        bev = self.bev_dilated if dilated else self.bev
        out = np.ones(len(idx), dtype=bool)
        ii = idx[inside]
        out[inside] = bev[ii[:, 0], ii[:, 1]]
        return out

    def column_height(self, xy: np.ndarray) -> np.ndarray:
        """(N, 2) metres -> (N,) highest point z in the column (-inf where empty or outside)."""
        idx, inside = self.column_of(xy)
        out = np.full(len(idx), -np.inf)
        ii = idx[inside]
        out[inside] = self.height[ii[:, 0], ii[:, 1]]
        return out

    def is_free(self, points: np.ndarray) -> np.ndarray:
        """(N, 3) metres -> (N,) bool: inside the map, above the flight floor, not in a dilated obstacle."""
        points = np.atleast_2d(points)
        return ~self.dilated.is_occupied(points) & (points[:, 2] >= self.min_flight_z)


def scale_points(points: np.ndarray, ratio: float) -> np.ndarray:
    """Point cloud units -> metres (official `pcd_scale_ratio`)."""
    return np.asarray(points, dtype=np.float64)[:, :3] * float(ratio)


def remove_sparse_points(points: np.ndarray, voxel_size: float, min_neighbors: int) -> np.ndarray:
    """Drop points whose 3x3x3 voxel neighbourhood holds fewer than `min_neighbors` other points.

    A grid-based stand-in for PCL's statistical outlier removal (k = 60, 2 sigma) of the official planner:
    isolated returns (lidar noise, floaters of a 3DGS cloud) vanish, surfaces stay.
    """
    if min_neighbors <= 0 or len(points) == 0:
        return points
    keys = np.floor(points / voxel_size).astype(np.int64)  # (N, 3)
    keys -= keys.min(axis=0)
    dims = keys.max(axis=0) + 3
    flat = ((keys[:, 0] + 1) * dims[1] + (keys[:, 1] + 1)) * dims[2] + (keys[:, 2] + 1)
    uniq, inverse, counts = np.unique(flat, return_inverse=True, return_counts=True)
    total = np.zeros(len(uniq), dtype=np.int64)
    for dx in (-1, 0, 1):
        for dy in (-1, 0, 1):
            for dz in (-1, 0, 1):
                neighbour = uniq + (dx * dims[1] + dy) * dims[2] + dz
                pos = np.clip(np.searchsorted(uniq, neighbour), 0, len(uniq) - 1)
                total += np.where(uniq[pos] == neighbour, counts[pos], 0)
    return points[(total[inverse] - 1) >= min_neighbors]


def resolve_bounds(cfg: MapConfig, scene_bounds: SceneBounds, elevation: float) -> SceneBounds:
    """The planning volume: config `MapBound` (or the scene's), with zmin replaced by the elevation."""
    b = cfg.bounds if cfg.bounds is not None else scene_bounds.as_list()
    return SceneBounds(b[0], b[1], b[2], b[3], float(elevation), b[5])


def dilate_grid(grid: OccupancyGrid, radius_m: float) -> OccupancyGrid:
    """`OccupancyGrid.dilate` (cube of ceil(radius / voxel) voxels) with in-place shifted ORs: ~9x faster.

    A separable max filter: along each axis, OR the grid shifted by 1..r voxels both ways.
    """
    r = int(math.ceil(radius_m / grid.voxel_size))
    occ = grid.occupied.copy()
    for axis in range(3):
        src = occ.copy() if r > 0 else occ
        for shift in range(1, r + 1):
            ahead = tuple(slice(shift, None) if a == axis else slice(None) for a in range(3))
            behind = tuple(slice(None, -shift) if a == axis else slice(None) for a in range(3))
            occ[ahead] |= src[behind]
            occ[behind] |= src[ahead]
    return OccupancyGrid(grid.origin.copy(), grid.voxel_size, occ, grid.outside_occupied)


def _dilate_2d(mask: np.ndarray, radius_vox: int) -> np.ndarray:
    if radius_vox <= 0:
        return mask.copy()
    kernel = np.ones((2 * radius_vox + 1, 2 * radius_vox + 1), np.uint8)
    return cv2.dilate(mask.astype(np.uint8), kernel).astype(bool)


def build_planning_map(
    points: np.ndarray, cfg: MapConfig, scene_bounds: SceneBounds, ground_z: float
) -> PlanningMap:
    """Build the planner's maps from a scene point cloud (N, 3) in point cloud units.

    Args:
        points: (N, 3) scene surface points (real scans or the embedded city's export).
        cfg: voxel width, dilate radius, bounds, elevation, min height threshold, scale ratio.
        scene_bounds: used when `cfg.bounds` is None.
        ground_z: used when `cfg.elevation_m` is None.
    """
    elevation = float(ground_z if cfg.elevation_m is None else cfg.elevation_m)
    points = scale_points(points, cfg.pcd_scale_ratio)
    points = remove_sparse_points(points, cfg.voxel_size_m, cfg.outlier_min_neighbors)
    bounds = resolve_bounds(cfg, scene_bounds, elevation)
    grid = OccupancyGrid.from_points(points, bounds, cfg.voxel_size_m, outside_occupied=True)
    dilated = dilate_grid(grid, cfg.dilate_radius_m)

    min_flight_z = elevation + cfg.min_height_thresh_m
    above = points[points[:, 2] >= min_flight_z]
    idx, inside = grid.index_of(above)
    idx, above = idx[inside], above[inside]
    bev = np.zeros(grid.shape[:2], dtype=bool)
    bev[idx[:, 0], idx[:, 1]] = True
    height = np.full(grid.shape[:2], -np.inf)
    np.maximum.at(height, (idx[:, 0], idx[:, 1]), above[:, 2])
    radius_vox = int(math.ceil(cfg.dilate_radius_m / cfg.voxel_size_m))
    return PlanningMap(grid, dilated, bev, _dilate_2d(bev, radius_vox), height, elevation, min_flight_z)
