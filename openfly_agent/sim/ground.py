"""The ground map of a city: an RGBA raster of roads, sidewalks, parks, ponds and plazas (1 texel = 1 m).

RGB is the base colour; alpha holds the region kind times 32 (the ground shader adds lane markings,
ripples or grain per kind). Row j covers world y in [origin_y + j * texel, ...), column i covers x.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

KIND_OUTER, KIND_ROAD, KIND_SIDEWALK, KIND_PARK, KIND_WATER, KIND_PLAZA = range(6)
KIND_COLORS = {
    KIND_OUTER: (112, 128, 84),
    KIND_ROAD: (66, 66, 72),
    KIND_SIDEWALK: (158, 152, 142),
    KIND_PARK: (88, 148, 66),
    KIND_WATER: (42, 94, 156),
    KIND_PLAZA: (184, 172, 156),
}
PATH_COLOR = (186, 168, 130)
_REGION_KINDS = {"road": KIND_ROAD, "block": KIND_SIDEWALK, "park": KIND_PARK, "water": KIND_WATER}


@dataclass(frozen=True)
class GroundMap:
    """rgba (H, W, 4) uint8; origin (x, y) metres of texel (0, 0)'s corner; texel_m metres per texel."""

    rgba: np.ndarray
    origin: tuple[float, float]
    texel_m: float

    @property
    def size_m(self) -> tuple[float, float]:
        return self.rgba.shape[1] * self.texel_m, self.rgba.shape[0] * self.texel_m


def _paint(
    rgba: np.ndarray, origin, texel: float, lo, hi, kind: int, color=None, ellipse: bool = False
) -> None:
    i0, j0 = (int(np.floor((lo[k] - origin[k]) / texel)) for k in (0, 1))
    i1, j1 = (int(np.ceil((hi[k] - origin[k]) / texel)) for k in (0, 1))
    i0, j0, i1, j1 = max(i0, 0), max(j0, 0), min(i1, rgba.shape[1]), min(j1, rgba.shape[0])
    if i1 <= i0 or j1 <= j0:
        return
    value = np.array([*(color or KIND_COLORS[kind]), kind * 32], dtype=np.uint8)
    if not ellipse:
        rgba[j0:j1, i0:i1] = value
        return
    xs = origin[0] + (np.arange(i0, i1) + 0.5) * texel
    ys = origin[1] + (np.arange(j0, j1) + 0.5) * texel
    cx, cy, rx, ry = (lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, (hi[0] - lo[0]) / 2, (hi[1] - lo[1]) / 2
    inside = ((xs[None, :] - cx) / rx) ** 2 + ((ys[:, None] - cy) / ry) ** 2 <= 1.0
    rgba[j0:j1, i0:i1][inside] = value


def _value_noise(rng: np.random.Generator, shape: tuple[int, int], cell: int) -> np.ndarray:
    """(H, W) float32 smooth noise in [0, 1] with features about `cell` texels wide (bilinear value noise)."""
    coarse = rng.random((shape[0] // cell + 2, shape[1] // cell + 2), dtype=np.float32)
    return cv2.resize(
        coarse, (coarse.shape[1] * cell, coarse.shape[0] * cell), interpolation=cv2.INTER_LINEAR
    )[: shape[0], : shape[1]]


def _add_grain(rgba: np.ndarray, seed: int) -> None:
    """Multiply RGB by two octaves of noise (grass, asphalt and paving are never flat; motion shows)."""
    rng = np.random.default_rng(seed)
    shape = rgba.shape[:2]
    grain = 0.5 * _value_noise(rng, shape, 2) + 0.5 * _value_noise(rng, shape, 8)  # (H, W)
    kind = rgba[..., 3] // 32
    strength = np.where(kind == KIND_PARK, 0.5, np.where(kind == KIND_WATER, 0.1, 0.25)).astype(np.float32)
    scale = 1.0 + strength * (grain - 0.5)  # (H, W)
    rgba[..., :3] = np.clip(rgba[..., :3] * scale[..., None], 0, 255).astype(np.uint8)


def rasterize_ground(city, texel_m: float = 1.0, margin_m: float = 24.0) -> GroundMap:
    """The ground map of `city` (any object with bounds, roads, blocks, parks, water, plazas)."""
    b = city.bounds
    origin = (b.xmin - margin_m, b.ymin - margin_m)
    width = int(np.ceil((b.xmax - b.xmin + 2 * margin_m) / texel_m))
    height = int(np.ceil((b.ymax - b.ymin + 2 * margin_m) / texel_m))
    rgba = np.empty((height, width, 4), dtype=np.uint8)
    rgba[:] = (*KIND_COLORS[KIND_OUTER], KIND_OUTER * 32)
    for region in (*city.blocks, *city.roads):
        kind = _REGION_KINDS[region.kind] if region.kind != "water" else KIND_PARK  # ponds sit in a lawn
        _paint(rgba, origin, texel_m, region.lo, region.hi, kind)
    for plaza in city.plazas:
        _paint(rgba, origin, texel_m, plaza.lo, plaza.hi, KIND_PLAZA)
    for park in city.parks:  # two crossing footpaths, 3 m wide
        cx, cy = (park.lo[0] + park.hi[0]) / 2, (park.lo[1] + park.hi[1]) / 2
        _paint(rgba, origin, texel_m, (park.lo[0], cy - 1.5), (park.hi[0], cy + 1.5), KIND_PLAZA, PATH_COLOR)
        _paint(rgba, origin, texel_m, (cx - 1.5, park.lo[1]), (cx + 1.5, park.hi[1]), KIND_PLAZA, PATH_COLOR)
    for pond in city.water:
        _paint(rgba, origin, texel_m, pond.lo, pond.hi, KIND_WATER, ellipse=pond.shape == "ellipse")
    _add_grain(rgba, seed=int(getattr(city, "seed", 0)) % (2**32))
    # the outermost texel ring stays 'outer' so clamp-to-edge sampling continues it beyond the map
    rgba[[0, -1], :] = (*KIND_COLORS[KIND_OUTER], 0)
    rgba[:, [0, -1]] = (*KIND_COLORS[KIND_OUTER], 0)
    return GroundMap(rgba, origin, float(texel_m))
