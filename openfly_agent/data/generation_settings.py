"""What the readers of a toolchain-made dataset need of its generation settings: its frame size and the
parameters of its embedded cities, for whoever rebuilds its scenes (eval's simulator, training's attribute
targets; sim/embedded_scenes.py turns them into a city config).

The toolchain writes them as `GenerationSettings` beside the data (`constants.GENERATION_SETTINGS_JSON`), next to
its full config (`constants.TOOLCHAIN_CONFIG_JSON`, the record it resumes against). A dataset generated before
the record existed has the full config only: `read_generation_settings` then reads the same values from it.
"""

from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass
from pathlib import Path

from openfly_agent import constants as C
from openfly_agent.utils.errors import RecordError


@dataclass(frozen=True)
class GenerationSettings:
    """The generation settings a dataset's readers depend on."""

    width: int  # frame width, pixels (toolchain `render.width`)
    height: int  # frame height, pixels (`render.height`)
    city_size_m: float  # side of each embedded city (`scenes.city_size_m`)
    city_buildings: int | None = None  # per city (`scenes.city_buildings`); None = the generator's default

    def save(self, root: str | Path) -> Path:
        """Write the record into the dataset under `root`; returns its path."""
        path = Path(root) / C.GENERATION_SETTINGS_JSON
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps(dataclasses.asdict(self), indent=2, sort_keys=True) + "\n")
        return path


# GenerationSettings field -> (section, key) of the toolchain's full config, the older datasets' only record
_IN_TOOLCHAIN_CONFIG = {
    "width": ("render", "width"),
    "height": ("render", "height"),
    "city_size_m": ("scenes", "city_size_m"),
    "city_buildings": ("scenes", "city_buildings"),
}
_TYPES = {"width": int, "height": int, "city_size_m": float, "city_buildings": int}


def read_generation_settings(root: str | Path) -> GenerationSettings | None:
    """The generation settings of the dataset under `root`; None when it has neither record (a dataset the
    toolchain did not make, such as the released OpenFly data).

    Raises:
        RecordError: the record is not a JSON object, or a setting is missing or of the wrong type (the message
            names the file and the field).
    """
    path = Path(root) / C.GENERATION_SETTINGS_JSON
    if path.is_file():
        values = _json_object(path)
    elif (Path(root) / C.TOOLCHAIN_CONFIG_JSON).is_file():  # generated before the record existed
        path = Path(root) / C.TOOLCHAIN_CONFIG_JSON
        config = _json_object(path)
        sections = {name: part for name, part in config.items() if isinstance(part, dict)}
        values = {
            name: sections.get(section, {}).get(key) for name, (section, key) in _IN_TOOLCHAIN_CONFIG.items()
        }
    else:
        return None
    typed = {}
    for name, kind in _TYPES.items():
        value = values.get(name)
        if value is None and name != "city_buildings":
            raise RecordError(path, None, name, "missing")
        if value is not None and (isinstance(value, bool) or not isinstance(value, (int, float))):
            raise RecordError(path, None, name, f"expected a number, got {value!r}")
        typed[name] = None if value is None else kind(value)
    return GenerationSettings(**typed)


def _json_object(path: Path) -> dict:
    try:
        data = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as err:
        raise RecordError(path, None, "<json>", f"not valid JSON ({err})") from err
    if not isinstance(data, dict):
        raise RecordError(path, None, "<json>", "expected a JSON object")
    return data
