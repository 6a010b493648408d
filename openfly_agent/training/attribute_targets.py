"""The target landmark's attributes as class ids, for the grounding head's attribute loss
(`model.grounding.attribute_weight`; model/grounding/head.py, `attribute_loss`).

Embedded cities are generated from their seed, so a (scene id, landmark id) pair names a landmark whose colour,
type, size and feature the city knows (sim/embedded_scenes.py); the ids index the landmark vocabularies of
constants.py (`LANDMARK_VOCABULARIES`), in the order of `model.grounding.attribute_classes`. Other scenes (the
released OpenFly data) have none: their ids are -1, which the loss skips.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from openfly_agent import constants as C
from openfly_agent.data.generation_settings import read_generation_settings
from openfly_agent.sim.embedded_scenes import EmbeddedScenes, city_config
from openfly_agent.sim.scene import Landmark

ATTRIBUTE_FIELDS = C.LANDMARK_ATTRIBUTE_FIELDS  # the `Landmark` fields, in the order of the ids
UNKNOWN = np.full(len(C.LANDMARK_VOCABULARIES), -1, dtype=np.int64)
_CLASS_IDS = [{name: k for k, name in enumerate(vocabulary)} for vocabulary in C.LANDMARK_VOCABULARIES]


def vocabulary_sizes() -> list[int]:
    """Classes of each attribute: what `model.grounding.attribute_classes` must say."""
    return [len(vocabulary) for vocabulary in C.LANDMARK_VOCABULARIES]


def attribute_ids(landmark: Landmark) -> np.ndarray:
    """(4,) int64 class ids of a landmark's colour, type, size and feature (-1 for a value outside the vocabulary)."""
    values = [getattr(landmark, name) for name in ATTRIBUTE_FIELDS]
    return np.array([ids.get(value, -1) for ids, value in zip(_CLASS_IDS, values)], dtype=np.int64)


class LandmarkAttributes:
    """(scene id, landmark id) -> (4,) int64 attribute ids of a dataset's landmarks, -1 when unknown (called).

    Args:
        scenes: the dataset's embedded scenes (`for_dataset` builds them from its saved settings).
    """

    def __init__(self, scenes: EmbeddedScenes) -> None:
        self.scenes = scenes
        self._ids: dict[str, dict[str, np.ndarray]] = {}

    @classmethod
    def for_dataset(cls, root: str | Path) -> LandmarkAttributes:
        """The lookup for a toolchain-made dataset (its saved city settings).

        Raises:
            FileNotFoundError: `root` holds no generation settings (not a dataset the toolchain made).
            RecordError: its generation settings are not readable.
        """
        settings = read_generation_settings(root)
        if settings is None:
            raise FileNotFoundError(
                f"{Path(root) / C.GENERATION_SETTINGS_JSON} not found: the attributes come from the cities of a "
                "dataset made by the toolchain (python -m openfly_agent.toolchain generate)"
            )
        return cls(EmbeddedScenes(city_config(settings.city_size_m, settings.city_buildings)))

    def __call__(self, scene_id: str, landmark_id: str) -> np.ndarray:
        if scene_id not in self._ids:
            landmarks = self.scenes.landmarks(scene_id)
            self._ids[scene_id] = {key: attribute_ids(landmark) for key, landmark in landmarks.items()}
        return self._ids[scene_id].get(landmark_id, UNKNOWN)
