"""sim/embedded_scenes.py: what training and eval read of the embedded cities, checked against the city itself."""

from __future__ import annotations

from openfly_agent import constants as C
from openfly_agent.sim.city import COLORS, FEATURES, SIZES, TYPES, CityConfig, generate_city
from openfly_agent.sim.embedded_scenes import EmbeddedScenes, city_config, scene_obstacles

SMALL = CityConfig(size_m=300.0, n_buildings=20)


def test_city_config_takes_the_two_city_settings_and_defaults_the_rest():
    assert city_config(1000.0) == CityConfig()
    assert city_config(300, 20) == SMALL


def test_landmarks_and_obstacles_are_the_citys_own():
    city = generate_city(5, SMALL)
    scenes = EmbeddedScenes(SMALL)
    assert scenes.city("embedded-5") is scenes.city("embedded-5")  # generated once
    assert list(scenes.landmarks("embedded-5")) == [b.landmark_id for b in city.buildings]
    obstacles = scene_obstacles("embedded-5", SMALL)
    buildings = [o for o in obstacles if o.kind == "building"]
    trees = [o for o in obstacles if o.kind == "tree"]
    assert len(buildings) == len(city.buildings) and len(trees) == len(city.trees) > 0
    first = city.buildings[0]
    assert buildings[0].lo == tuple(first.lo.tolist()) and buildings[0].hi == tuple(first.hi.tolist())
    assert buildings[0].landmark_id == first.landmark_id
    tree = city.trees[0]  # trunk and canopy: the box holds both parts
    assert trees[0].hi[2] == max(part.hi[2] for part in tree.parts)
    assert trees[0].lo[2] == min(part.lo[2] for part in tree.parts)


def test_a_scene_that_is_not_embedded_has_no_city():
    scenes = EmbeddedScenes()
    assert scenes.city("real-city/Map") is None and scenes.landmarks("real-city/Map") == {}
    assert scene_obstacles("real-city/Map") == [] and scene_obstacles("embedded-x") == []


def test_the_city_draws_its_landmarks_from_the_shared_vocabularies():
    assert tuple(COLORS) == C.LANDMARK_COLORS  # the attribute ids of training batches index these
    assert C.LANDMARK_VOCABULARIES[1:] == (TYPES, SIZES, FEATURES)
    for landmark in EmbeddedScenes(SMALL).landmarks("embedded-5").values():
        values = [getattr(landmark, name) for name in C.LANDMARK_ATTRIBUTE_FIELDS]
        assert all(v in vocab for v, vocab in zip(values, C.LANDMARK_VOCABULARIES))
