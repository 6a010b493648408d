"""The generation settings a toolchain-made dataset saved beside its data (`constants.TOOLCHAIN_CONFIG_JSON`):
its frame size and its embedded cities' parameters, for whoever rebuilds its scenes (eval's simulator,
training's attribute targets; sim/embedded_scenes.py turns them into a city config)."""

from __future__ import annotations

import json
from pathlib import Path

from openfly_agent import constants as C
from openfly_agent.utils.errors import RecordError


def generation_settings(root: str | Path) -> dict | None:
    """Frame size and city parameters the dataset under `root` was generated with; None when it has no
    toolchain config (the released OpenFly data).

    Returns keys `width`, `height`, `city_size_m`, `city_buildings`, `collision_voxel_m` (those present).

    Raises:
        RecordError: the file is not a toolchain config.
    """
    path = Path(root) / C.TOOLCHAIN_CONFIG_JSON
    if not path.is_file():
        return None
    try:
        data = json.loads(path.read_text())
        render, scenes = data.get("render", {}), data.get("scenes", {})
    except (json.JSONDecodeError, AttributeError) as err:
        raise RecordError(path, None, "<json>", f"not a toolchain config: {err}") from err
    out = {"width": render.get("width"), "height": render.get("height")}
    out.update(
        city_size_m=scenes.get("city_size_m"),
        city_buildings=scenes.get("city_buildings"),
        collision_voxel_m=scenes.get("collision_voxel_m"),
    )
    return {k: v for k, v in out.items() if v is not None}
