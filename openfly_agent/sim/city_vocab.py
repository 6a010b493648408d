"""Closed vocabularies of the embedded city (colours, types, sizes, shapes, features) and render materials.

Instructions may only name attributes from these tuples; every attribute is visible in the render
(colour of the facade, height class, footprint shape, rooftop feature). The landmark attribute words and their
order are constants.py's (`LANDMARK_*`: the grounding batches' attribute ids index them); this module gives
them their looks. `city.py` re-exports them.
"""

from __future__ import annotations

from openfly_agent import constants as C

# Facade colour of each named colour (the names and their order: constants.LANDMARK_COLORS) -> RGB in [0, 1],
# chosen to stay distinct at 64-224 px under the sun shading.
_FACADE_RGB: dict[str, tuple[float, float, float]] = {
    "red": (0.78, 0.16, 0.13),
    "orange": (0.93, 0.50, 0.12),
    "yellow": (0.93, 0.82, 0.22),
    "green": (0.22, 0.58, 0.28),
    "blue": (0.18, 0.36, 0.78),
    "purple": (0.50, 0.26, 0.64),
    "pink": (0.94, 0.55, 0.70),
    "white": (0.93, 0.93, 0.91),
    "gray": (0.54, 0.55, 0.57),
    "black": (0.13, 0.13, 0.15),
    "brown": (0.50, 0.31, 0.18),
    "beige": (0.86, 0.77, 0.58),
}
COLORS: dict[str, tuple[float, float, float]] = {name: _FACADE_RGB[name] for name in C.LANDMARK_COLORS}
# Relative frequency of each colour (real cities are mostly gray / beige / white).
COLOR_WEIGHTS: dict[str, float] = {
    "red": 1.0, "orange": 0.6, "yellow": 0.6, "green": 0.5, "blue": 0.9, "purple": 0.4,
    "pink": 0.4, "white": 1.6, "gray": 2.0, "black": 0.7, "brown": 1.0, "beige": 1.6,
}  # fmt: skip

# Types follow from geometry (see `building_type`), so a name always matches what is rendered.
TYPES: tuple[str, ...] = C.LANDMARK_TYPES
# Height classes (metres): low-rise < 20 <= mid-rise < 60 <= high-rise.
SIZES: tuple[str, ...] = C.LANDMARK_SIZES
SHAPES: tuple[str, ...] = ("rectangular", "square", "L-shaped", "stepped", "cylindrical")
FEATURES: tuple[str, ...] = C.LANDMARK_FEATURES

LOW_RISE_MAX_M = 20.0
MID_RISE_MAX_M = 60.0
TALL_MIN_M = 100.0  # towers and skyscrapers start here
SLENDER_MAX_SIDE_M = 30.0  # a tall building whose shorter side is below this is a "tower"

# Fragment-shader materials of box parts (the renderer switches on these integers).
MATERIAL_PLAIN = 0  # flat shaded (roof equipment, spires, domes)
MATERIAL_WINDOWS = 1  # facade with a procedural window grid
MATERIAL_GLASS = 2  # curtain wall: glass with thin mullions
MATERIAL_FOLIAGE = 3  # tree canopies, rooftop gardens (noisy green)
MATERIAL_BILLBOARD = 4  # bright striped advertising panel
MATERIAL_STRIPED = 5  # red / white banded mast

# Colours of non-landmark things.
FEATURE_COLORS: dict[str, tuple[float, float, float]] = {
    "spire": (0.80, 0.82, 0.85),
    "dome": (0.85, 0.68, 0.25),
    "antenna": (0.85, 0.20, 0.18),
    "water tank": (0.45, 0.30, 0.20),
    "rooftop garden": (0.30, 0.60, 0.22),
    "billboard": (0.98, 0.92, 0.30),
    "billboard frame": (0.25, 0.25, 0.27),
}
TRUNK_COLOR = (0.36, 0.25, 0.15)
CANOPY_COLORS = ((0.20, 0.45, 0.18), (0.26, 0.52, 0.20), (0.17, 0.40, 0.22), (0.32, 0.50, 0.16))


def size_of_height(height_m: float) -> str:
    """Height class of a building: 'low-rise', 'mid-rise' or 'high-rise'."""
    if height_m < LOW_RISE_MAX_M:
        return "low-rise"
    if height_m < MID_RISE_MAX_M:
        return "mid-rise"
    return "high-rise"


def building_type(height_m: float, side_a_m: float, side_b_m: float, feature: str) -> str:
    """Type name implied by the geometry (and a glass facade for offices)."""
    short_side = min(side_a_m, side_b_m)
    area = side_a_m * side_b_m
    if height_m >= TALL_MIN_M:
        return "tower" if short_side < SLENDER_MAX_SIDE_M else "skyscraper"
    if height_m < 12.0 and area < 450.0:
        return "house"
    if height_m < 16.0 and area >= 1500.0:
        return "warehouse"
    if feature == "glass facade":
        return "office building"
    return "building"
