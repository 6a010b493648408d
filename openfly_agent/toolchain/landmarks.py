"""Landmark segmentation by BEV projection + contour extraction (official `seg_gen`), and landmark geometry.

BEV mode of the official tool: keep the points above elevation + min_height_thresh, rasterise them at
`bev_voxel_size`, erode 3x3 twice, take the external contours; each blob's centroid is a landmark, its
height the highest point within +- 5 m of the centroid.
"""

from __future__ import annotations

import math

import cv2
import numpy as np

from openfly_agent.sim.scene import Landmark, SceneBounds
from openfly_agent.toolchain.config import SegmentationConfig

SEGMENTED_PREFIX = "seg-"


def landmark_top(landmark: Landmark) -> float:
    """Roof height: `position.z` for landmark lists (zero extent), box centre + half height for city boxes."""
    return float(landmark.position[2] + 0.5 * landmark.extent[2])


def landmark_xy(landmark: Landmark) -> np.ndarray:
    """(2,) footprint centre."""
    return np.array(landmark.position[:2], dtype=np.float64)


def _rasterise(points: np.ndarray, bounds: SceneBounds, cell: float) -> tuple[np.ndarray, np.ndarray]:
    """Points -> (NY, NX) uint8 occupancy image (row = y) and (NY, NX) max-z image (-inf where empty)."""
    nx = max(1, math.ceil((bounds.xmax - bounds.xmin) / cell))
    ny = max(1, math.ceil((bounds.ymax - bounds.ymin) / cell))
    ix = np.floor((points[:, 0] - bounds.xmin) / cell).astype(np.int64)
    iy = np.floor((points[:, 1] - bounds.ymin) / cell).astype(np.int64)
    keep = (ix >= 0) & (ix < nx) & (iy >= 0) & (iy < ny)
    ix, iy, z = ix[keep], iy[keep], points[keep, 2]
    image = np.zeros((ny, nx), dtype=np.uint8)
    image[iy, ix] = 255
    top = np.full((ny, nx), -np.inf)
    np.maximum.at(top, (iy, ix), z)
    return image, top


def segment_landmarks(
    points: np.ndarray,
    bounds: SceneBounds,
    min_z: float,
    bev_voxel_size: float,
    cfg: SegmentationConfig | None = None,
) -> list[Landmark]:
    """Landmarks from a point cloud in metres: one per external contour of the eroded BEV map.

    Args:
        points: (N, 3) metres.
        bounds: x-y extent of the BEV image.
        min_z: elevation + min_height_thresh; lower points are ground / clutter.
        bev_voxel_size: BEV pixel size in metres.
        cfg: erosion, minimum area and height window.

    Returns:
        Landmarks `seg-0000`, ... with `position` = (centroid x, centroid y, instance height), `extent` =
        (bounding box dx, dy, 0) and `attributes` {"area_m2", "footprint" (K, 2) world polygon}; the
        descriptive fields are "building" / "unknown" (a VLM or a list names them).
    """
    cfg = cfg or SegmentationConfig()
    points = np.asarray(points, dtype=np.float64)
    image, top = _rasterise(points[points[:, 2] >= min_z], bounds, bev_voxel_size)
    if cfg.erode_iterations:
        image = cv2.erode(image, np.ones((3, 3), np.uint8), iterations=cfg.erode_iterations)
    contours, _ = cv2.findContours(image, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
    window = max(0, int(math.ceil(cfg.height_window_m / bev_voxel_size)))
    origin = np.array([bounds.xmin, bounds.ymin])
    landmarks = []
    for contour in contours:
        area_m2 = cv2.contourArea(contour) * bev_voxel_size**2
        moments = cv2.moments(contour)
        if area_m2 < cfg.min_area_m2 or moments["m00"] <= 0:
            continue
        cx, cy = moments["m10"] / moments["m00"], moments["m01"] / moments["m00"]  # pixel (col, row)
        col, row = int(cx), int(cy)
        patch = top[max(0, row - window) : row + window + 1, max(0, col - window) : col + window + 1]
        height = float(patch.max()) if np.isfinite(patch).any() else float(top[np.isfinite(top)].max())
        polygon = origin + (contour[:, 0, :].astype(np.float64) + 0.5) * bev_voxel_size  # (K, 2) world x, y
        lo, hi = polygon.min(axis=0), polygon.max(axis=0)
        centre = origin + (np.array([cx, cy]) + 0.5) * bev_voxel_size
        landmarks.append(
            Landmark(
                landmark_id=f"{SEGMENTED_PREFIX}{len(landmarks):04d}",
                type="building",
                color="unknown",
                size="unknown",
                shape="unknown",
                feature="none",
                position=(float(centre[0]), float(centre[1]), height),
                extent=(float(hi[0] - lo[0]), float(hi[1] - lo[1]), 0.0),
                attributes={"area_m2": float(area_m2), "footprint": polygon},
            )
        )
    return landmarks
