"""The target landmark's attributes as class ids, for the grounding head's attribute loss
(`model.grounding.attribute_weight`; model/grounding.py, `attribute_loss`).

Embedded cities are generated from their seed, so a (scene id, landmark id) pair names a landmark whose colour,
type, size and feature the city generator knows; the ids index the city's vocabularies (sim/city_vocab.py), in
the order of `model.grounding.attribute_classes`. Other scenes (the released OpenFly data) have none: their ids
are -1, which the loss skips.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from openfly_agent.sim.city import COLORS, FEATURES, SIZES, TYPES, CityConfig, generate_city, parse_scene_id
from openfly_agent.toolchain.grounding import source_render_settings

logger = logging.getLogger(__name__)

VOCABULARIES = (tuple(COLORS), TYPES, SIZES, FEATURES)  # colour, type, size, feature
ATTRIBUTE_FIELDS = ("color", "type", "size", "feature")  # the `Landmark` fields, in the same order
UNKNOWN = np.full(len(VOCABULARIES), -1, dtype=np.int64)


def vocabulary_sizes() -> list[int]:
    """Classes of each attribute: what `model.grounding.attribute_classes` must say."""
    return [len(vocabulary) for vocabulary in VOCABULARIES]


class LandmarkAttributes:
    """(scene id, landmark id) -> (4,) int64 attribute ids of an embedded city's landmark, -1 when unknown.

    Args:
        city_config: the city settings the dataset was generated with (`for_dataset` reads them).
    """

    def __init__(self, city_config: CityConfig) -> None:
        self.city_config = city_config
        self._scenes: dict[str, dict[str, np.ndarray]] = {}

    @classmethod
    def for_dataset(cls, root: str | Path) -> LandmarkAttributes:
        """The lookup for a toolchain-made dataset (its saved city settings)."""
        _, _, city_config = source_render_settings(root)
        return cls(city_config)

    def __call__(self, scene_id: str, landmark_id: str) -> np.ndarray:
        return self._scene(scene_id).get(landmark_id, UNKNOWN)

    def _scene(self, scene_id: str) -> dict[str, np.ndarray]:
        if scene_id not in self._scenes:
            try:
                seed = parse_scene_id(scene_id)
            except ValueError:
                self._scenes[scene_id] = {}  # not an embedded city: no attributes
                return self._scenes[scene_id]
            index = [{name: k for k, name in enumerate(vocabulary)} for vocabulary in VOCABULARIES]
            table = {}
            for building in generate_city(seed, self.city_config).buildings:
                landmark = building.landmark
                values = [getattr(landmark, name) for name in ATTRIBUTE_FIELDS]
                table[landmark.landmark_id] = np.array(
                    [ids.get(value, -1) for ids, value in zip(index, values)], dtype=np.int64
                )
            self._scenes[scene_id] = table
        return self._scenes[scene_id]
