"""The target landmark's attributes as class ids, for the grounding head's attribute loss
(`model.grounding.attribute_weight`; model/grounding/head.py, `attribute_loss`).

Embedded cities are generated from their seed, so a (scene id, landmark id) pair names a landmark whose colour,
type, size and feature the city generator knows; the ids index the city's vocabularies (sim/city_vocab.py), in
the order of `model.grounding.attribute_classes`. Other scenes (the released OpenFly data) have none: their ids
are -1, which the loss skips.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from openfly_agent.sim.city import (
    COLORS,
    FEATURES,
    SIZES,
    TYPES,
    City,
    CityConfig,
    generate_city,
    parse_scene_id,
)
from openfly_agent.sim.scene import Landmark
from openfly_agent.toolchain.grounding import source_render_settings

VOCABULARIES = (tuple(COLORS), TYPES, SIZES, FEATURES)  # colour, type, size, feature
ATTRIBUTE_FIELDS = ("color", "type", "size", "feature")  # the `Landmark` fields, in the same order
UNKNOWN = np.full(len(VOCABULARIES), -1, dtype=np.int64)
_CLASS_IDS = [{name: k for k, name in enumerate(vocabulary)} for vocabulary in VOCABULARIES]


def vocabulary_sizes() -> list[int]:
    """Classes of each attribute: what `model.grounding.attribute_classes` must say."""
    return [len(vocabulary) for vocabulary in VOCABULARIES]


def attribute_ids(landmark: Landmark) -> np.ndarray:
    """(4,) int64 class ids of a landmark's colour, type, size and feature (-1 for a value outside the vocabulary)."""
    values = [getattr(landmark, name) for name in ATTRIBUTE_FIELDS]
    return np.array([ids.get(value, -1) for ids, value in zip(_CLASS_IDS, values)], dtype=np.int64)


class LandmarkAttributes:
    """The embedded cities of a dataset, generated once per scene: their `City`, their landmarks, and (called)
    (scene id, landmark id) -> (4,) int64 attribute ids, -1 when unknown.

    Args:
        city_config: the city settings the dataset was generated with (`for_dataset` reads them).
    """

    def __init__(self, city_config: CityConfig) -> None:
        self.city_config = city_config
        self._cities: dict[str, City | None] = {}
        self._landmarks: dict[str, dict[str, Landmark]] = {}
        self._ids: dict[str, dict[str, np.ndarray]] = {}

    @classmethod
    def for_dataset(cls, root: str | Path) -> LandmarkAttributes:
        """The lookup for a toolchain-made dataset (its saved city settings)."""
        _, _, city_config = source_render_settings(root)
        return cls(city_config)

    def __call__(self, scene_id: str, landmark_id: str) -> np.ndarray:
        if scene_id not in self._ids:
            landmarks = self.landmarks(scene_id)
            self._ids[scene_id] = {key: attribute_ids(landmark) for key, landmark in landmarks.items()}
        return self._ids[scene_id].get(landmark_id, UNKNOWN)

    def city(self, scene_id: str) -> City | None:
        """The embedded city of `scene_id` (None for a scene that is not one: no attributes)."""
        if scene_id not in self._cities:
            try:
                seed = parse_scene_id(scene_id)
            except ValueError:
                self._cities[scene_id] = None
            else:
                self._cities[scene_id] = generate_city(seed, self.city_config)
        return self._cities[scene_id]

    def landmarks(self, scene_id: str) -> dict[str, Landmark]:
        """landmark id -> `Landmark` of the scene's city (empty for a scene that is not embedded)."""
        if scene_id not in self._landmarks:
            city = self.city(scene_id)
            buildings = city.buildings if city is not None else ()
            self._landmarks[scene_id] = {b.landmark.landmark_id: b.landmark for b in buildings}
        return self._landmarks[scene_id]
