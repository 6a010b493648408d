"""Landmark segmentation by BEV projection + contour extraction (official `seg_gen`), and landmark geometry.

BEV mode of the official tool: keep the points above elevation + min_height_thresh, rasterise them at
`bev_voxel_size`, erode 3x3 twice, take the external contours; each blob's centroid is a landmark, its
height the highest point within +- 5 m of the centroid.
"""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

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


def fill_landmark_heights(landmarks: list[Landmark], pmap, window_m: float = 5.0) -> list[Landmark]:
    """Give landmarks without a height (list z at or below the ground, e.g. UE / 3DGS lists) the highest
    map point within +- `window_m` of their x-y position, as the official segmentation measures it.

    Args:
        landmarks: landmarks in metres.
        pmap: a `PlanningMap` (its column height map).
        window_m: half size of the square searched around each landmark.
    """
    filled = []
    r = max(0, int(math.ceil(window_m / pmap.voxel_size)))
    for lm in landmarks:
        if landmark_top(lm) > pmap.elevation:
            filled.append(lm)
            continue
        idx, inside = pmap.column_of(np.array(lm.position[:2]))
        i, j = (int(v) for v in idx[0])
        patch = pmap.height[max(0, i - r) : i + r + 1, max(0, j - r) : j + r + 1] if inside[0] else None
        if patch is None or not np.isfinite(patch).any():
            filled.append(lm)
            continue
        top = float(patch.max())
        filled.append(
            dataclasses.replace(
                lm, position=(lm.position[0], lm.position[1], top), extent=(*lm.extent[:2], 0.0)
            )
        )
    return filled


def write_landmark_list(path, landmarks: list[Landmark], pcd_scale_ratio: float = 1.0) -> None:
    """Write landmarks as an official `seg_map` JSONL (AirSim / 3DGS convention: point cloud units).

    Each line: {"type", "color", "size", "shape", "feature", "filename": "X=<x>Y=<y>Z=<z>.png"} with the
    position divided by `pcd_scale_ratio`, so `sim.real_scene.read_landmark_list` reads it back.
    """
    lines = []
    for lm in landmarks:
        x, y, z = (v / pcd_scale_ratio for v in lm.position)
        record = {k: getattr(lm, k) or "test" for k in ("type", "color", "size", "shape", "feature")}
        record["filename"] = f"X={x!r}Y={y!r}Z={z!r}.png"
        lines.append(json.dumps(record))
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("\n".join(lines) + ("\n" if lines else ""), encoding="utf-8")
