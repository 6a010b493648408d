"""Map backgrounds for the top-down plots: building footprints of embedded scenes."""

from __future__ import annotations

import numpy as np

from openfly_agent.eval.plots import Footprint
from openfly_agent.sim.city import SCENE_PREFIX, generate_city, parse_scene_id


def scene_footprints(scene_id: str, city_config=None) -> list[Footprint]:
    """Footprints of every building and tree of an `embedded-<seed>` scene; [] for other scenes.

    Args:
        scene_id: the episode's scene id.
        city_config: the `CityConfig` the dataset was generated with (None = the default); a different one
            gives a different city.
    """
    if not scene_id.startswith(SCENE_PREFIX):
        return []
    city = generate_city(parse_scene_id(scene_id), city_config)
    buildings = [
        Footprint(
            float(b.lo[0]), float(b.lo[1]), float(b.hi[0]), float(b.hi[1]),
            height_m=float(b.hi[2]), landmark_id=b.landmark_id,
        )
        for b in city.buildings
    ]  # fmt: skip
    trees = []
    for tree in city.trees:  # obstacles too: the union of trunk and canopy boxes
        lo = np.min([part.lo for part in tree.parts], axis=0)
        hi = np.max([part.hi for part in tree.parts], axis=0)
        trees.append(
            Footprint(float(lo[0]), float(lo[1]), float(hi[0]), float(hi[1]), float(hi[2]), kind="tree")
        )
    return buildings + trees


class FootprintCache:
    """Footprints per scene id, generated once per evaluation (a city takes a fraction of a second)."""

    def __init__(self, city_config=None):
        self.city_config = city_config
        self._by_scene: dict[str, list[Footprint]] = {}

    def __call__(self, scene_id: str) -> list[Footprint]:
        if scene_id not in self._by_scene:
            self._by_scene[scene_id] = scene_footprints(scene_id, self.city_config)
        return self._by_scene[scene_id]
