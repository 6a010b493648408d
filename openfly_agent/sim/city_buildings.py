"""Geometry of one procedural building: footprint shape + rooftop feature as axis-aligned box parts.

Every part is an axis-aligned box (metres, world frame), so the renderer draws it as one instanced cube
and the occupancy grid marks it exactly. Round shapes (cylinders, domes) are staircases of boxes.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from openfly_agent.sim import city_vocab as V


@dataclass(frozen=True)
class BoxPart:
    """One axis-aligned box of a building or tree: [lo, hi] in metres, a colour and a render material."""

    lo: tuple[float, float, float]
    hi: tuple[float, float, float]
    color: tuple[float, float, float]
    material: int = V.MATERIAL_PLAIN


def _box(x0, y0, z0, x1, y1, z1, color, material) -> BoxPart:
    lo = (float(min(x0, x1)), float(min(y0, y1)), float(min(z0, z1)))
    hi = (float(max(x0, x1)), float(max(y0, y1)), float(max(z0, z1)))
    return BoxPart(lo, hi, tuple(float(c) for c in color), int(material))


def _disc(cx, cy, radius, z0, z1, color, material) -> list[BoxPart]:
    """A vertical cylinder as the union of 3 boxes whose corners lie on the circle (15, 45, 75 degrees)."""
    parts = []
    for deg in (15.0, 45.0, 75.0):
        hx, hy = radius * math.cos(math.radians(deg)), radius * math.sin(math.radians(deg))
        parts.append(_box(cx - hx, cy - hy, z0, cx + hx, cy + hy, z1, color, material))
    return parts


def body_parts(
    rng: np.random.Generator,
    shape: str,
    footprint: tuple[float, float, float, float],
    height_m: float,
    color: tuple[float, float, float],
    material: int,
) -> list[BoxPart]:
    """Box parts of the body for `shape` inside `footprint` (x0, y0, x1, y1), from z = 0 to `height_m`."""
    x0, y0, x1, y1 = footprint
    dx, dy = x1 - x0, y1 - y0
    if shape in ("rectangular", "square"):
        return [_box(x0, y0, 0.0, x1, y1, height_m, color, material)]
    if shape == "L-shaped":
        a, b = rng.uniform(0.4, 0.6, size=2)
        wing_height = height_m * rng.uniform(0.6, 1.0)
        flip_x, flip_y = rng.integers(0, 2, size=2)
        # wing 1: full width along x at the low (or high) y side; wing 2: full depth along y at one x side.
        ya, yb = (y0, y0 + a * dy) if not flip_y else (y1 - a * dy, y1)
        xa, xb = (x0, x0 + b * dx) if not flip_x else (x1 - b * dx, x1)
        return [
            _box(x0, ya, 0.0, x1, yb, height_m, color, material),
            _box(xa, y0, 0.0, xb, y1, wing_height, color, material),
        ]
    if shape == "stepped":
        tiers = (0.55, 0.8, 1.0) if height_m >= 40.0 else (0.65, 1.0)
        inset_step = 0.14 * min(dx, dy)
        parts, z = [], 0.0
        for k, top_frac in enumerate(tiers):
            inset = k * inset_step
            top = height_m * top_frac
            parts.append(_box(x0 + inset, y0 + inset, z, x1 - inset, y1 - inset, top, color, material))
            z = top
        return parts
    if shape == "cylindrical":
        return _disc((x0 + x1) / 2, (y0 + y1) / 2, min(dx, dy) / 2, 0.0, height_m, color, material)
    raise ValueError(f"unknown building shape {shape!r}; expected one of {V.SHAPES}")


def _roof(parts: list[BoxPart]) -> tuple[float, float, float, float, float]:
    """(x0, y0, x1, y1, z) of the highest part's top face."""
    top = max(parts, key=lambda p: p.hi[2])
    return top.lo[0], top.lo[1], top.hi[0], top.hi[1], top.hi[2]


def feature_parts(rng: np.random.Generator, feature: str, body: list[BoxPart]) -> list[BoxPart]:
    """Box parts of a rooftop `feature` on the highest roof of `body` (none for none / glass facade)."""
    if feature in ("none", "glass facade"):
        return []
    x0, y0, x1, y1, z = _roof(body)
    cx, cy = (x0 + x1) / 2, (y0 + y1) / 2
    side = min(x1 - x0, y1 - y0)
    body_height = max(p.hi[2] for p in body)
    col = V.FEATURE_COLORS
    if feature == "rooftop billboard":
        along_x = (x1 - x0) >= (y1 - y0)
        half = 0.35 * max(x1 - x0, y1 - y0)
        panel_h = float(np.clip(0.3 * side, 4.0, 12.0))
        hx, hy = (half, 0.4) if along_x else (0.4, half)
        frame = _box(cx - hx, cy - hy, z, cx + hx, cy + hy, z + 1.5, col["billboard frame"], V.MATERIAL_PLAIN)
        panel = _box(
            cx - hx,
            cy - hy,
            z + 1.5,
            cx + hx,
            cy + hy,
            z + 1.5 + panel_h,
            col["billboard"],
            V.MATERIAL_BILLBOARD,
        )
        return [frame, panel]
    if feature == "spire":
        base_half = 0.15 * side
        base_top = z + max(3.0, 0.04 * body_height)
        needle_half = max(0.6, 0.03 * side)
        needle_top = base_top + max(12.0, 0.12 * body_height)
        return [
            _box(cx - base_half, cy - base_half, z, cx + base_half, cy + base_half, base_top, col["spire"],
                 V.MATERIAL_PLAIN),
            _box(cx - needle_half, cy - needle_half, base_top, cx + needle_half, cy + needle_half, needle_top,
                 col["spire"], V.MATERIAL_PLAIN),
        ]  # fmt: skip
    if feature == "dome":
        radius = 0.4 * side
        parts = []
        for k, h0 in enumerate((0.0, 0.35, 0.65, 0.87)):  # stacked squares inscribed in a hemisphere
            h1 = (0.35, 0.65, 0.87, 1.0)[k]
            half = radius * math.sqrt(max(0.0, 1.0 - h0 * h0)) / math.sqrt(2.0) * 1.25
            parts.append(_box(cx - half, cy - half, z + h0 * radius, cx + half, cy + half, z + h1 * radius,
                              col["dome"], V.MATERIAL_PLAIN))  # fmt: skip
        return parts
    if feature == "antenna":
        mast_top = z + max(10.0, 0.12 * body_height)
        return [
            _box(
                cx - 2.0, cy - 2.0, z, cx + 2.0, cy + 2.0, z + 2.0, col["billboard frame"], V.MATERIAL_PLAIN
            ),
            _box(
                cx - 0.6, cy - 0.6, z + 2.0, cx + 0.6, cy + 0.6, mast_top, col["antenna"], V.MATERIAL_STRIPED
            ),
        ]
    if feature == "water tank":
        half = float(np.clip(0.15 * side, 1.5, 4.0))
        ox, oy = rng.uniform(-0.2, 0.2, size=2) * side
        return _disc(
            cx + ox, cy + oy, half, z + 1.5, z + 1.5 + 2.4 * half, col["water tank"], V.MATERIAL_PLAIN
        )
    if feature == "rooftop garden":
        inset = min(1.5, 0.15 * side)
        return [_box(x0 + inset, y0 + inset, z, x1 - inset, y1 - inset, z + 0.8, col["rooftop garden"],
                 V.MATERIAL_FOLIAGE)]  # fmt: skip
    raise ValueError(f"unknown building feature {feature!r}; expected one of {V.FEATURES}")


def tree_parts(x: float, y: float, height_m: float, canopy_m: float, color) -> list[BoxPart]:
    """A tree: a thin trunk and a box canopy covering the top 60 % of its height."""
    trunk_top = 0.45 * height_m
    return [
        _box(x - 0.3, y - 0.3, 0.0, x + 0.3, y + 0.3, trunk_top, V.TRUNK_COLOR, V.MATERIAL_PLAIN),
        _box(x - canopy_m / 2, y - canopy_m / 2, 0.4 * height_m, x + canopy_m / 2, y + canopy_m / 2, height_m,
             color, V.MATERIAL_FOLIAGE),
    ]  # fmt: skip
