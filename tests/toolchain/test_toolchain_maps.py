"""Voxel map, BEV map and landmark segmentation on hand-made point clouds."""

from __future__ import annotations

import numpy as np
import pytest
from toolchain_scene import BOUNDS, BUILDINGS, box_surface_points, synthetic_scene

from openfly_agent.sim.scene import SceneBounds
from openfly_agent.toolchain.config import MapConfig, SegmentationConfig
from openfly_agent.toolchain.landmarks import landmark_top, segment_landmarks
from openfly_agent.toolchain.voxel_map import build_planning_map, remove_sparse_points, resolve_bounds


def test_bounds_take_zmin_from_the_elevation():
    cfg = MapConfig(bounds=[-10, 10, -5, 5, -200, 50])
    assert resolve_bounds(cfg, BOUNDS, elevation=-48.0).as_list() == [-10, 10, -5, 5, -48.0, 50]
    assert resolve_bounds(MapConfig(), BOUNDS, 0.0) == BOUNDS


def test_voxel_map_marks_points_dilates_and_keeps_low_points_out_of_the_bev():
    points = np.array([[1.0, 1.0, 10.0], [5.0, 5.0, 2.0]])  # one high point, one below the 6 m threshold
    bounds = SceneBounds(0, 20, 0, 20, 0, 20)
    pmap = build_planning_map(
        points, MapConfig(voxel_size_m=2.0, dilate_radius_m=3.0, min_height_thresh_m=6.0), bounds, 0.0
    )
    assert pmap.grid.shape == (10, 10, 10)
    assert pmap.grid.occupied.sum() == 2
    assert pmap.grid.occupied[0, 0, 5] and pmap.grid.occupied[2, 2, 1]
    # ceil(3 / 2) = 2 voxels each way: the high point's cube is clipped at the border -> 3 x 3 x 5
    assert pmap.dilated.occupied[:3, :3, 3:8].all() and not pmap.dilated.occupied[3, 0, 5]
    assert pmap.bev.sum() == 1 and pmap.bev[0, 0]  # the 2 m point is below elevation + 6 m
    assert pmap.bev_dilated.sum() == 9  # 3 x 3 after clipping
    assert pmap.column_height(np.array([[1.0, 1.0], [15.0, 15.0]])).tolist() == [10.0, -np.inf]
    assert pmap.min_flight_z == 6.0
    # outside the bounds and below the flight floor count as blocked
    assert not pmap.is_free(np.array([[30.0, 1.0, 10.0]]))[0]
    assert not pmap.is_free(np.array([[15.0, 15.0, 4.0]]))[0]
    assert pmap.is_free(np.array([[15.0, 15.0, 10.0]]))[0]


def test_scale_ratio_converts_point_units():
    points = np.array([[100.0, 100.0, 1000.0]])  # centimetres
    pmap = build_planning_map(
        points,
        MapConfig(voxel_size_m=1.0, dilate_radius_m=0, pcd_scale_ratio=0.01),
        SceneBounds(0, 5, 0, 5, 0, 20),
        0.0,
    )
    assert pmap.grid.occupied[1, 1, 10] and pmap.grid.occupied.sum() == 1


def test_sparse_points_are_removed_surfaces_kept():
    surface = box_surface_points((0, 0, 0), (10, 10, 10), spacing=1.0)
    noise = np.array([[50.0, 50.0, 50.0], [-40.0, 3.0, 7.0]])
    kept = remove_sparse_points(np.concatenate([surface, noise]), voxel_size=2.0, min_neighbors=5)
    assert len(kept) == len(surface)
    assert remove_sparse_points(noise, 2.0, 0) is noise


def test_segmentation_finds_each_building_with_centroid_and_height():
    points, landmarks, _ = synthetic_scene()
    found = segment_landmarks(points, BOUNDS, min_z=6.0, bev_voxel_size=2.0, cfg=SegmentationConfig())
    assert len(found) == len(BUILDINGS)
    for _, lo, hi, *_ in BUILDINGS:
        centre = (np.array(lo[:2]) + np.array(hi[:2])) / 2
        match = min(found, key=lambda lm: np.linalg.norm(np.array(lm.position[:2]) - centre))
        assert np.linalg.norm(np.array(match.position[:2]) - centre) < 2.0  # within one BEV pixel
        assert match.position[2] == pytest.approx(hi[2])  # instance height = highest point near the centroid
        assert landmark_top(match) == pytest.approx(hi[2])
        area = (hi[0] - lo[0]) * (hi[1] - lo[1])
        # eroded twice (a pixel per side each), so smaller
        assert 0.4 * area < match.attributes["area_m2"] < area
    assert landmark_top(landmarks[0]) == pytest.approx(60.0)  # box centre + half height


def test_segmentation_erosion_removes_thin_structures():
    # 5 m thick: 3 BEV pixels, gone after 2 erosions
    wall = box_surface_points((0, 0, 0), (60, 5, 20), spacing=1.0)
    found = segment_landmarks(
        wall, BOUNDS, min_z=6.0, bev_voxel_size=2.0, cfg=SegmentationConfig(min_area_m2=0)
    )
    assert found == []
    kept = segment_landmarks(
        wall, BOUNDS, min_z=6.0, bev_voxel_size=2.0, cfg=SegmentationConfig(erode_iterations=0, min_area_m2=0)
    )
    assert len(kept) == 1
