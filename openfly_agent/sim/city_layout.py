"""Street grid, block kinds (buildings, park, water, plaza) and lots of the procedural city.

A square city of side `size_m` centred on the origin is cut by a regular road grid into blocks; a few
blocks become parks or ponds, the rest are split into lots that each hold one building (spare lots
become plazas). Pure numpy, deterministic given the random generator.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

logger = logging.getLogger(__name__)

MAX_LOTS_PER_SIDE = 4


@dataclass(frozen=True)
class GroundRegion:
    """A flat ground area: kind 'road' | 'park' | 'water' | 'plaza' | 'block', axis-aligned [lo, hi] in x-y.

    `shape` is 'rect' or 'ellipse' (the ellipse inscribed in the rectangle, used for ponds).
    """

    kind: str
    lo: tuple[float, float]
    hi: tuple[float, float]
    shape: str = "rect"

    def contains(self, xy: np.ndarray) -> np.ndarray:
        """(N, 2) metres -> (N,) bool."""
        xy = np.atleast_2d(xy)
        lo, hi = np.asarray(self.lo), np.asarray(self.hi)
        if self.shape == "ellipse":
            centre, half = (lo + hi) / 2, (hi - lo) / 2
            return (((xy - centre) / half) ** 2).sum(axis=1) <= 1.0
        return np.all((xy >= lo) & (xy <= hi), axis=1)


@dataclass(frozen=True)
class Lot:
    """A parcel for one building: [x0, x1] x [y0, y1] metres, and the block it belongs to."""

    x0: float
    y0: float
    x1: float
    y1: float
    block: int

    @property
    def min_side(self) -> float:
        return min(self.x1 - self.x0, self.y1 - self.y0)


@dataclass(frozen=True)
class Layout:
    """Roads, blocks by kind and the lots chosen for buildings."""

    roads: list[GroundRegion]
    blocks: list[GroundRegion]  # every block footprint (kind 'block', 'park' or 'water')
    parks: list[GroundRegion]
    water: list[GroundRegion]
    plazas: list[GroundRegion]
    lots: list[Lot]


def _grid(size_m: float, block_m: float) -> tuple[int, float, float]:
    """(blocks per side, actual pitch, x of the first road centre)."""
    n = max(1, int(size_m // block_m))
    return n, size_m / n, -size_m / 2


def _pick_kinds(rng: np.random.Generator, n_blocks: int, park_fraction: float, water_fraction: float):
    """Block index -> 'block' | 'park' | 'water'; at least one park and one pond from 4 blocks on."""
    at_least = 1 if n_blocks >= 4 else 0
    n_park = max(at_least, int(round(park_fraction * n_blocks)))
    n_water = max(at_least, int(round(water_fraction * n_blocks)))
    order = rng.permutation(n_blocks)
    kinds = ["block"] * n_blocks
    for k in order[:n_park]:
        kinds[k] = "park"
    for k in order[n_park : n_park + n_water]:
        kinds[k] = "water"
    return kinds


def _lot_counts(rng: np.random.Generator, n_build_blocks: int, target: int) -> np.ndarray:
    """(n_build_blocks, 2) lots per side, grown at random until there are >= `target` lots (if possible)."""
    counts = rng.integers(1, 4, size=(n_build_blocks, 2))
    while counts.prod(axis=1).sum() < target:
        growable = np.flatnonzero(counts.min(axis=1) < MAX_LOTS_PER_SIDE)
        if len(growable) == 0:
            break
        b = rng.choice(growable)
        counts[b, np.argmin(counts[b])] += 1
    return counts


def make_layout(
    rng: np.random.Generator,
    size_m: float,
    block_m: float,
    road_m: float,
    sidewalk_m: float,
    park_fraction: float,
    water_fraction: float,
    n_buildings: int,
) -> Layout:
    """Roads, block kinds and exactly `n_buildings` lots (fewer, with a warning, if they do not fit)."""
    n, pitch, x_first = _grid(size_m, block_m)
    half = size_m / 2
    roads = []
    for k in range(n + 1):
        c = x_first + k * pitch
        roads.append(
            GroundRegion("road", (c - road_m / 2, -half - road_m / 2), (c + road_m / 2, half + road_m / 2))
        )
        roads.append(
            GroundRegion("road", (-half - road_m / 2, c - road_m / 2), (half + road_m / 2, c + road_m / 2))
        )
    kinds = _pick_kinds(rng, n * n, park_fraction, water_fraction)
    blocks, parks, water, build_blocks = [], [], [], []
    for b in range(n * n):
        i, j = b % n, b // n
        lo = (x_first + i * pitch + road_m / 2, x_first + j * pitch + road_m / 2)
        hi = (lo[0] + pitch - road_m, lo[1] + pitch - road_m)
        region = GroundRegion(kinds[b], lo, hi, "ellipse" if kinds[b] == "water" else "rect")
        blocks.append(region)
        {"park": parks, "water": water, "block": build_blocks}[kinds[b]].append((b, region))
    counts = _lot_counts(rng, len(build_blocks), n_buildings)
    all_lots = []
    for (b, region), (nx, ny) in zip(build_blocks, counts):
        x0, y0 = region.lo[0] + sidewalk_m, region.lo[1] + sidewalk_m
        dx = (region.hi[0] - region.lo[0] - 2 * sidewalk_m) / nx
        dy = (region.hi[1] - region.lo[1] - 2 * sidewalk_m) / ny
        all_lots += [
            Lot(x0 + a * dx, y0 + c * dy, x0 + (a + 1) * dx, y0 + (c + 1) * dy, b)
            for a in range(nx)
            for c in range(ny)
        ]
    if len(all_lots) < n_buildings:
        logger.warning(
            "city of %.0f m holds only %d of %d requested buildings", size_m, len(all_lots), n_buildings
        )
    chosen = np.sort(rng.permutation(len(all_lots))[: min(n_buildings, len(all_lots))])
    spare = sorted(set(range(len(all_lots))) - set(chosen.tolist()))
    plazas = [
        GroundRegion("plaza", (all_lots[k].x0, all_lots[k].y0), (all_lots[k].x1, all_lots[k].y1))
        for k in spare
    ]
    return Layout(
        roads=roads,
        blocks=blocks,
        parks=[r for _, r in parks],
        water=[r for _, r in water],
        plazas=plazas,
        lots=[all_lots[k] for k in chosen],
    )
