import numpy as np

from openfly_agent.sim.occupancy import OccupancyGrid
from openfly_agent.sim.scene import SceneBounds

BOUNDS = SceneBounds(0, 10, 0, 10, 0, 10)


def test_from_points_marks_the_voxel_of_each_point():
    grid = OccupancyGrid.from_points(np.array([[0.5, 0.5, 0.5], [9.9, 9.9, 9.9], [20, 0, 0]]), BOUNDS, 1.0)
    assert grid.shape == (10, 10, 10)
    assert grid.occupied.sum() == 2  # the point outside the bounds is ignored
    assert grid.is_occupied(np.array([[0.1, 0.9, 0.2], [1.1, 0.5, 0.5]])).tolist() == [True, False]


def test_outside_counts_as_occupied_only_when_asked():
    inside_free = OccupancyGrid.empty(BOUNDS, 1.0)
    assert not inside_free.is_occupied(np.array([[-5.0, 0, 0]]))[0]
    strict = OccupancyGrid.empty(BOUNDS, 1.0, outside_occupied=True)
    assert strict.is_occupied(np.array([[-5.0, 0, 0]]))[0]


def test_dilate_inflates_by_ceil_radius_over_voxel():
    grid = OccupancyGrid.empty(BOUNDS, 1.0)
    grid.occupied[5, 5, 5] = True
    grown = grid.dilate(1.5)  # ceil(1.5 / 1) = 2 voxels each way -> a 5x5x5 cube
    assert grown.occupied.sum() == 125
    assert grown.occupied[3, 7, 5] and not grown.occupied[2, 5, 5]
    assert grid.occupied.sum() == 1  # the original is untouched


def test_segment_collision_and_ground():
    grid = OccupancyGrid.empty(BOUNDS, 1.0)
    grid.mark_box(np.array([4.0, 4.0, 0.0]), np.array([6.0, 6.0, 8.0]))
    assert grid.segment_collides(np.array([1.0, 5.0, 5.0]), np.array([9.0, 5.0, 5.0]))
    assert not grid.segment_collides(np.array([1.0, 5.0, 9.0]), np.array([9.0, 5.0, 9.0]))
    assert grid.segment_collides(np.array([1.0, 1.0, 2.0]), np.array([1.0, 1.0, -1.0]), ground_z=0.0)


def test_bev_projects_columns_above_a_height():
    grid = OccupancyGrid.empty(BOUNDS, 1.0)
    grid.occupied[2, 3, 1] = True
    grid.occupied[7, 7, 6] = True
    assert grid.bev().sum() == 2
    assert grid.bev(min_z=4.0).sum() == 1
