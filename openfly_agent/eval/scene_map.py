"""Map backgrounds for the top-down plots: building footprints of embedded scenes."""

from __future__ import annotations

from openfly_agent.eval.plots import Footprint
from openfly_agent.sim.embedded_scenes import scene_obstacles


def scene_footprints(scene_id: str, city_config=None) -> list[Footprint]:
    """Footprints of every building and tree of an `embedded-<seed>` scene; [] for other scenes.

    Args:
        scene_id: the episode's scene id.
        city_config: the `CityConfig` the dataset was generated with (None = the default); a different one
            gives a different city.
    """
    return [
        Footprint(
            o.lo[0], o.lo[1], o.hi[0], o.hi[1], height_m=o.hi[2], landmark_id=o.landmark_id, kind=o.kind
        )
        for o in scene_obstacles(scene_id, city_config)
    ]


class FootprintCache:
    """Footprints per scene id, generated once per evaluation (a city takes a fraction of a second)."""

    def __init__(self, city_config=None):
        self.city_config = city_config
        self._by_scene: dict[str, list[Footprint]] = {}

    def __call__(self, scene_id: str) -> list[Footprint]:
        if scene_id not in self._by_scene:
            self._by_scene[scene_id] = scene_footprints(scene_id, self.city_config)
        return self._by_scene[scene_id]
