"""The embedded scenes as the layers above sim/ see them: the city settings of a generated dataset, and the
landmarks and obstacle boxes of a scene by its id (training's attribute targets, eval's map plots).

The procedural city (city*.py) stays behind these functions: training and eval never import it
(tests/test_layering.py).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from openfly_agent.sim.city import SCENE_PREFIX, City, CityConfig, generate_city, parse_scene_id
from openfly_agent.sim.scene import Landmark


def city_config(size_m: float, buildings: int | None = None) -> CityConfig:
    """The `CityConfig` of embedded cities of side `size_m` with `buildings` buildings (None: the generator's
    default), the two city settings the toolchain takes and a generated dataset records
    (data/generation_settings.py)."""
    if buildings is None:
        return CityConfig(size_m=float(size_m))
    return CityConfig(size_m=float(size_m), n_buildings=int(buildings))


EMBEDDED_SCENE_FORM = f"{SCENE_PREFIX}<seed>"  # how an embedded scene id reads, for messages


def is_embedded_scene(scene_id: str) -> bool:
    """Whether `scene_id` names an embedded city (`embedded-<seed>`), the only scenes the embedded simulator flies."""
    try:
        parse_scene_id(scene_id)
    except ValueError:
        return False
    return True


def embedded_city(scene_id: str, config: CityConfig | None = None) -> City | None:
    """The city of an `embedded-<seed>` scene (None for any other scene id: a real scene has none)."""
    try:
        seed = parse_scene_id(scene_id)
    except ValueError:
        return None
    return generate_city(seed, config)


class EmbeddedScenes:
    """The cities of a dataset's scenes, generated once per scene id with one `CityConfig`.

    Args:
        config: the city settings the dataset was generated with (`city_config`; None: the defaults).
    """

    def __init__(self, config: CityConfig | None = None) -> None:
        self.config = config
        self._cities: dict[str, City | None] = {}
        self._landmarks: dict[str, dict[str, Landmark]] = {}

    def city(self, scene_id: str) -> City | None:
        """The city of `scene_id` (None for a scene that is not embedded)."""
        if scene_id not in self._cities:
            self._cities[scene_id] = embedded_city(scene_id, self.config)
        return self._cities[scene_id]

    def landmarks(self, scene_id: str) -> dict[str, Landmark]:
        """landmark id -> `Landmark` of the scene's city (empty for a scene that is not embedded)."""
        if scene_id not in self._landmarks:
            city = self.city(scene_id)
            buildings = city.buildings if city is not None else ()
            self._landmarks[scene_id] = {b.landmark.landmark_id: b.landmark for b in buildings}
        return self._landmarks[scene_id]


@dataclass(frozen=True)
class Obstacle:
    """An axis-aligned box around one building or tree of a city, in metres."""

    lo: tuple[float, float, float]
    hi: tuple[float, float, float]
    kind: str  # building | tree
    landmark_id: str = ""  # buildings only


def scene_obstacles(scene_id: str, config: CityConfig | None = None) -> list[Obstacle]:
    """The box of every building, then every tree (the union of trunk and canopy), of an embedded scene;
    [] for a scene that is not embedded. `config`: the city settings of the dataset (a different one gives a
    different city)."""
    city = embedded_city(scene_id, config)
    if city is None:
        return []
    obstacles = [
        Obstacle(tuple(map(float, b.lo)), tuple(map(float, b.hi)), "building", b.landmark_id)
        for b in city.buildings
    ]
    for tree in city.trees:
        lo = np.min([part.lo for part in tree.parts], axis=0)
        hi = np.max([part.hi for part in tree.parts], axis=0)
        obstacles.append(Obstacle(tuple(map(float, lo)), tuple(map(float, hi)), "tree"))
    return obstacles
