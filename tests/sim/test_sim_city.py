"""The procedural city: determinism, ranges, vocabularies, layout sanity, occupancy and point cloud."""

import numpy as np
import pytest

from openfly_agent.sim import city_vocab as V
from openfly_agent.sim.city import (
    COLORS,
    FEATURES,
    SHAPES,
    SIZES,
    TYPES,
    City,
    CityConfig,
    generate_city,
    make_box_building,
    parse_scene_id,
    scene_id_of,
)
from openfly_agent.sim.pointcloud import sample_box_surfaces
from openfly_agent.sim.scene import SceneBounds

TINY = CityConfig(size_m=300.0, n_buildings=30, n_trees=40)


@pytest.fixture(scope="module")
def city():
    return generate_city(3)


def _box_city(*buildings) -> City:
    return City("test-1", SceneBounds(-50, 50, -50, 50, 0, 100), tuple(buildings))


def test_same_seed_same_city_other_seed_other_city():
    a, b, c = generate_city(11, TINY), generate_city(11, TINY), generate_city(12, TINY)
    for key, value in a.box_table().items():
        np.testing.assert_array_equal(value, b.box_table()[key])
    assert [lm.description() for lm in a.landmarks] == [lm.description() for lm in b.landmarks]
    assert a.box_table()["lo"].shape != c.box_table()["lo"].shape or not np.array_equal(
        a.box_table()["lo"], c.box_table()["lo"]
    )


def test_default_city_size_heights_and_counts(city):
    b = city.bounds
    assert b.xmax - b.xmin >= 1000 and b.ymax - b.ymin >= 1000 and b.zmax >= 300
    assert city.scene_id == "embedded-3" and city.seed == 3
    assert len(city.buildings) == 300  # hundreds of buildings, exactly as configured
    heights = np.array([lm.attributes["height_m"] for lm in city.landmarks])
    assert heights.min() < 8.0 and heights.max() > 200.0
    assert np.mean((heights >= 5) & (heights <= 60)) > 0.8  # mostly 5-60 m
    assert 1 <= np.sum(heights >= 100) <= 40
    assert city.roads and city.parks and city.water and len(city.trees) == 400
    assert max(float(bd.hi[2]) for bd in city.buildings) < city.bounds.zmax


def test_attributes_come_from_the_closed_vocabularies_and_match_geometry(city):
    ids = [lm.landmark_id for lm in city.landmarks]
    assert len(set(ids)) == len(ids)
    seen = {k: set() for k in ("color", "type", "size", "shape", "feature")}
    for bd in city.buildings:
        lm = bd.landmark
        assert lm.color in COLORS and lm.type in TYPES and lm.size in SIZES
        assert lm.shape in SHAPES and lm.feature in FEATURES
        for k in seen:
            seen[k].add(getattr(lm, k))
        np.testing.assert_allclose(lm.position, (bd.lo + bd.hi) / 2)
        np.testing.assert_allclose(lm.extent, bd.hi - bd.lo)
        h = lm.attributes["height_m"]
        assert lm.size == V.size_of_height(h)
        if lm.type in ("tower", "skyscraper"):
            assert h >= 100
        if lm.type == "house":
            assert h < 12
        if lm.feature in ("spire", "dome", "antenna", "water tank", "rooftop garden", "rooftop billboard"):
            assert lm.attributes["top_m"] > h  # the feature stands on the roof, so it is visible
        if lm.feature == "glass facade":
            assert any(p.material == V.MATERIAL_GLASS for p in bd.parts)
        assert city.landmark(lm.landmark_id) is lm
    assert len(seen["color"]) >= 10 and len(seen["shape"]) == len(SHAPES) and len(seen["feature"]) >= 7
    with pytest.raises(KeyError, match="embedded-3"):
        city.landmark("nope")


def _overlap_xy(lo_a, hi_a, lo_b, hi_b) -> np.ndarray:
    """(A, B) bool: the x-y rectangles overlap with positive area."""
    return np.all(
        (np.minimum(hi_a[:, None, :2], hi_b[None, :, :2]) - np.maximum(lo_a[:, None, :2], lo_b[None, :, :2]))
        > 1e-6,
        axis=2,
    )


def test_buildings_trees_roads_water_do_not_overlap(city):
    lo = np.array([b.lo for b in city.buildings])
    hi = np.array([b.hi for b in city.buildings])
    overlap = _overlap_xy(lo, hi, lo, hi)
    np.fill_diagonal(overlap, False)
    assert not overlap.any()
    tree_lo = np.array([t.parts[1].lo for t in city.trees])
    tree_hi = np.array([t.parts[1].hi for t in city.trees])
    assert not _overlap_xy(tree_lo, tree_hi, lo, hi).any()
    centres = (lo + hi)[:, :2] / 2
    for region in (*city.roads, *city.water, *city.parks):
        assert not region.contains(centres).any()


def test_scene_ids_round_trip_and_reject_other_forms():
    assert parse_scene_id(scene_id_of(17)) == 17
    for bad in ("env_airsim_16", "embedded-", "embedded--3", "embedded-1.5"):
        with pytest.raises(ValueError, match="embedded-<non-negative integer>"):
            parse_scene_id(bad)


def test_config_errors_say_what_to_change():
    with pytest.raises(ValueError, match="size_m"):
        CityConfig(size_m=50.0)
    with pytest.raises(ValueError, match="park \\+ water"):
        CityConfig(park_fraction=0.5, water_fraction=0.5)


def test_occupancy_of_a_single_box_is_exact():
    city = _box_city(make_box_building(0, (10, 10, 0), (20, 20, 30), color="red"))
    grid = city.occupancy(2.0)
    assert grid.shape == (50, 50, 50)
    assert grid.occupied.sum() == 5 * 5 * 15  # the box covers exactly 5 x 5 x 15 voxels of 2 m
    probes = np.array([[15, 15, 29.9], [15, 15, 30.1], [9.9, 15, 5], [20.1, 15, 5]])
    assert grid.is_occupied(probes).tolist() == [True, False, False, False]
    assert city.occupancy(2.0) is grid  # cached


def test_point_cloud_samples_every_face_but_the_bottom():
    city = _box_city(make_box_building(0, (10, 10, 0), (20, 20, 30)))
    points = city.point_cloud(spacing=2.0)
    # walls: 6 x 16 samples each (10 m and 30 m with edges at <= 2 m), roof: 6 x 6
    assert len(points) == 4 * 6 * 16 + 6 * 6
    on_face = np.isin(points[:, 0], [10, 20]) | np.isin(points[:, 1], [10, 20]) | np.isclose(points[:, 2], 30)
    assert on_face.all() and points[:, 2].min() == 0
    with_ground = city.point_cloud(spacing=2.0, include_ground=True)
    assert len(with_ground) == len(points) + 50 * 50


def test_generated_point_cloud_lies_in_the_occupancy():
    city = generate_city(4, TINY)
    grid = city.occupancy(1.0)
    table = city.box_table()
    per_box = []
    for lo, hi in zip(table["lo"], table["hi"]):
        pts = sample_box_surfaces(lo[None], hi[None], 1.0)
        per_box.append(pts)
        inner = pts + 1e-3 * np.sign((lo + hi) / 2 - pts)  # 1 mm inside the box it samples
        assert grid.is_occupied(inner).all()
    np.testing.assert_array_equal(city.point_cloud(spacing=1.0), np.concatenate(per_box))
