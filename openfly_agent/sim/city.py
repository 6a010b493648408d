"""The procedural embedded city: one deterministic scene per integer seed (`embedded-<seed>`).

Buildings with named colours, types, sizes, shapes and rooftop features on a street grid with parks,
ponds, plazas and trees. Everything is axis-aligned boxes, so the renderer, the occupancy grid and the
point cloud all derive exactly from `City.box_table()`.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field

import numpy as np

from openfly_agent.sim import city_vocab as V
from openfly_agent.sim.city_buildings import BoxPart, body_parts, feature_parts, tree_parts
from openfly_agent.sim.city_layout import GroundRegion, Lot, make_layout
from openfly_agent.sim.city_vocab import COLORS, FEATURES, SHAPES, SIZES, TYPES
from openfly_agent.sim.occupancy import OccupancyGrid
from openfly_agent.sim.pointcloud import sample_box_surfaces
from openfly_agent.sim.scene import Landmark, SceneBounds

__all__ = [
    "COLORS", "FEATURES", "SHAPES", "SIZES", "TYPES", "BoxPart", "Building", "City", "CityConfig",
    "GroundRegion", "Tree", "generate_city", "make_box_building", "parse_scene_id", "scene_id_of",
]  # fmt: skip

SCENE_PREFIX = "embedded-"
_SCENE_RE = re.compile(r"^embedded-(\d+)$")


@dataclass
class CityConfig:
    """Seed-independent parameters of the procedural city (metres)."""

    size_m: float = 1000.0  # side of the square city, centred on the origin
    n_buildings: int = 300
    block_m: float = 100.0  # road grid pitch
    road_m: float = 14.0
    sidewalk_m: float = 4.0  # street trees stand on it; lots start behind it
    park_fraction: float = 0.08  # share of blocks that are parks
    water_fraction: float = 0.04  # share of blocks that are ponds
    tower_fraction: float = 0.06  # share of buildings that are 100-250 m towers / skyscrapers (at least one)
    n_trees: int = 400
    max_altitude_m: float = 300.0  # top of the scene bounds (flying volume)

    def __post_init__(self) -> None:
        if self.size_m < self.block_m:
            raise ValueError(f"CityConfig.size_m ({self.size_m}) must be >= block_m ({self.block_m})")
        if not 0 < self.road_m + 2 * self.sidewalk_m < 0.6 * self.block_m:
            raise ValueError("CityConfig.road_m + 2 * sidewalk_m must be positive and < 0.6 * block_m")
        fractions = (self.park_fraction, self.water_fraction, self.tower_fraction)
        if not all(0.0 <= f <= 1.0 for f in fractions) or self.park_fraction + self.water_fraction > 0.8:
            raise ValueError("CityConfig fractions must lie in [0, 1] and park + water <= 0.8")
        if self.n_buildings < 1 or self.n_trees < 0:
            raise ValueError("CityConfig.n_buildings must be >= 1 and n_trees >= 0")
        if self.max_altitude_m < 300.0:
            raise ValueError("CityConfig.max_altitude_m must be >= 300 (towers with spires reach ~290 m)")


@dataclass(frozen=True, eq=False)
class Building:
    """A landmark building: its `Landmark`, the AABB [lo, hi] (3,) of all parts, and the box parts."""

    landmark: Landmark
    lo: np.ndarray  # (3,) metres
    hi: np.ndarray  # (3,) metres
    parts: tuple[BoxPart, ...]
    index: int  # position in City.buildings; instance id in the renderer = index + 1

    @property
    def landmark_id(self) -> str:
        return self.landmark.landmark_id


@dataclass(frozen=True)
class Tree:
    """A tree (obstacle, not a landmark): trunk + canopy box parts."""

    x: float
    y: float
    height_m: float
    parts: tuple[BoxPart, ...]


@dataclass(frozen=True, eq=False)
class City:
    """An immutable scene. Build with `generate_city`, or directly for hand-made test scenes."""

    scene_id: str
    bounds: SceneBounds
    buildings: tuple[Building, ...]
    trees: tuple[Tree, ...] = ()
    roads: tuple[GroundRegion, ...] = ()
    parks: tuple[GroundRegion, ...] = ()
    water: tuple[GroundRegion, ...] = ()
    plazas: tuple[GroundRegion, ...] = ()
    blocks: tuple[GroundRegion, ...] = ()
    seed: int = -1  # -1 for hand-made scenes
    ground_z: float = 0.0
    config: CityConfig | None = None
    _cache: dict = field(default_factory=dict, repr=False)

    @property
    def landmarks(self) -> list[Landmark]:
        return [b.landmark for b in self.buildings]

    def landmark(self, landmark_id: str) -> Landmark:
        """The landmark with this id (KeyError naming the scene otherwise)."""
        return self.building(landmark_id).landmark

    def building(self, landmark_id: str) -> Building:
        index = self._cache.get("index")
        if index is None:
            index = self._cache["index"] = {b.landmark_id: b for b in self.buildings}
        if landmark_id not in index:
            raise KeyError(f"scene {self.scene_id} has no landmark {landmark_id!r}")
        return index[landmark_id]

    def box_table(self) -> dict[str, np.ndarray]:
        """Every box part of buildings then trees, as arrays (cached).

        Returns: lo (P, 3), hi (P, 3) float32 metres; color (P, 3) float32; material (P,) int32;
        instance (P,) int32 = building index + 1, 0 for trees.
        """
        if "boxes" not in self._cache:
            parts, ids = [], []
            for b in self.buildings:
                parts += b.parts
                ids += [b.index + 1] * len(b.parts)
            for t in self.trees:
                parts += t.parts
                ids += [0] * len(t.parts)
            self._cache["boxes"] = {
                "lo": np.array([p.lo for p in parts], dtype=np.float32).reshape(-1, 3),
                "hi": np.array([p.hi for p in parts], dtype=np.float32).reshape(-1, 3),
                "color": np.array([p.color for p in parts], dtype=np.float32).reshape(-1, 3),
                "material": np.array([p.material for p in parts], dtype=np.int32),
                "instance": np.array(ids, dtype=np.int32),
            }
        return self._cache["boxes"]

    def occupancy(self, voxel_size: float = 2.0) -> OccupancyGrid:
        """Voxel grid of buildings and trees over `bounds`, cached per voxel size; ground: z < ground_z."""
        key = ("occupancy", float(voxel_size))
        if key not in self._cache:
            grid = OccupancyGrid.empty(self.bounds, voxel_size)
            table = self.box_table()
            for lo, hi in zip(table["lo"].astype(np.float64), table["hi"].astype(np.float64)):
                grid.mark_box(lo, hi)
            self._cache[key] = grid
        return self._cache[key]

    def point_cloud(self, spacing: float = 2.0, include_ground: bool = False) -> np.ndarray:
        """(N, 3) float64 samples of every box surface (walls and roofs; ground on a grid if asked)."""
        table = self.box_table()
        points = sample_box_surfaces(table["lo"], table["hi"], spacing)
        if include_ground:
            b = self.bounds
            xs = np.arange(b.xmin + spacing / 2, b.xmax, spacing)
            ys = np.arange(b.ymin + spacing / 2, b.ymax, spacing)
            gx, gy = np.meshgrid(xs, ys, indexing="ij")
            ground = np.stack([gx.ravel(), gy.ravel(), np.full(gx.size, self.ground_z)], axis=1)
            points = np.concatenate([points, ground])
        return points


def scene_id_of(seed: int) -> str:
    """'embedded-<seed>'."""
    return f"{SCENE_PREFIX}{int(seed)}"


def parse_scene_id(scene_id: str) -> int:
    """'embedded-17' -> 17; a ValueError that names the expected form otherwise."""
    match = _SCENE_RE.match(str(scene_id))
    if not match:
        raise ValueError(
            f"not an embedded scene id: {scene_id!r} (expected 'embedded-<non-negative integer>')"
        )
    return int(match.group(1))


def make_box_building(
    index: int,
    lo,
    hi,
    color: str = "gray",
    type_name: str = "building",
    feature: str = "none",
    material: int = V.MATERIAL_WINDOWS,
    landmark_id: str | None = None,
) -> Building:
    """A single-box building (for hand-made scenes and tests); no rooftop geometry is added for `feature`."""
    lo, hi = np.asarray(lo, dtype=np.float64), np.asarray(hi, dtype=np.float64)
    part = BoxPart(tuple(lo.tolist()), tuple(hi.tolist()), COLORS[color], material)
    return _building(index, [part], color, type_name, feature, "rectangular", landmark_id)


def _building(index, parts, color, type_name, feature, shape, landmark_id=None) -> Building:
    lo = np.min([p.lo for p in parts], axis=0)
    hi = np.max([p.hi for p in parts], axis=0)
    facade_tops = [p.hi[2] for p in parts if p.material in (V.MATERIAL_WINDOWS, V.MATERIAL_GLASS)]
    body_height = max(facade_tops) if facade_tops else float(hi[2])  # roof height without rooftop features
    landmark = Landmark(
        landmark_id=landmark_id or f"b{index:04d}",
        type=type_name,
        color=color,
        size=V.size_of_height(body_height),
        shape=shape,
        feature=feature,
        position=tuple(((lo + hi) / 2).tolist()),
        extent=tuple((hi - lo).tolist()),
        attributes={"height_m": float(body_height), "top_m": float(hi[2]), "index": index},
    )
    return Building(landmark, lo, hi, tuple(parts), index)


def _footprint(
    rng: np.random.Generator, lot: Lot, shape: str, tall: bool
) -> tuple[float, float, float, float]:
    """A footprint inside `lot`: 55-90 % of each side (towers <= 45 m), square for square / round shapes."""
    w, d = lot.x1 - lot.x0, lot.y1 - lot.y0
    fw, fd = w * rng.uniform(0.55, 0.9), d * rng.uniform(0.55, 0.9)
    if tall:
        fw, fd = min(fw, 45.0), min(fd, 45.0)
    if shape in ("square", "cylindrical"):
        fw = fd = min(fw, fd)
    elif shape in ("rectangular", "L-shaped") and max(fw, fd) < 1.2 * min(fw, fd):
        fw, fd = (fw, fw / 1.25) if fw >= fd else (fd / 1.25, fd)  # keep 'rectangular' visibly oblong
    fw, fd = max(fw, 6.0), max(fd, 6.0)
    x0 = lot.x0 + rng.uniform(0.0, max(0.0, w - fw))
    y0 = lot.y0 + rng.uniform(0.0, max(0.0, d - fd))
    return x0, y0, x0 + fw, y0 + fd


_FEATURE_WEIGHTS = {  # by height class: low / mid / tall
    "low": {"none": 5, "water tank": 1.5, "rooftop garden": 1.5, "rooftop billboard": 1, "dome": 0.5,
            "glass facade": 0.5},
    "mid": {"none": 3, "rooftop billboard": 1.5, "water tank": 1.2, "rooftop garden": 1, "dome": 0.8,
            "antenna": 1, "glass facade": 1.5},
    "tall": {"spire": 3, "antenna": 2, "glass facade": 2.5, "rooftop billboard": 1, "dome": 0.5, "none": 1},
}  # fmt: skip


def _weighted(rng: np.random.Generator, weights: dict[str, float]) -> str:
    names = list(weights)
    p = np.array([weights[n] for n in names], dtype=np.float64)
    return names[int(rng.choice(len(names), p=p / p.sum()))]


def _random_building(rng: np.random.Generator, index: int, lot: Lot, tower_height: float | None) -> Building:
    tall = tower_height is not None
    if tall:
        shape = _weighted(rng, {"rectangular": 2, "square": 2, "stepped": 2, "cylindrical": 1.5})
    elif lot.min_side < 22.0 and rng.random() < 0.75:
        shape = _weighted(rng, {"rectangular": 3, "square": 1, "L-shaped": 1.5})
    else:
        shape = _weighted(
            rng, {"rectangular": 3, "square": 1, "L-shaped": 1.5, "stepped": 1, "cylindrical": 0.7}
        )
    fp = _footprint(rng, lot, shape, tall)
    area = (fp[2] - fp[0]) * (fp[3] - fp[1])
    if tall:
        height = tower_height
    elif area < 450.0 and rng.random() < 0.7:
        height = rng.uniform(5.0, 11.5)  # houses
    elif area >= 1500.0 and rng.random() < 0.3:
        height = rng.uniform(6.0, 15.0)  # warehouses
    else:
        height = math.exp(rng.uniform(math.log(12.0), math.log(60.0)))
    feature = _weighted(rng, _FEATURE_WEIGHTS["tall" if tall else "mid" if height >= 20 else "low"])
    color_name = _weighted(rng, V.COLOR_WEIGHTS)
    color = tuple(np.clip(np.array(COLORS[color_name]) * rng.uniform(0.92, 1.06), 0.0, 1.0).tolist())
    material = V.MATERIAL_GLASS if feature == "glass facade" else V.MATERIAL_WINDOWS
    body = body_parts(rng, shape, fp, height, color, material)
    parts = body + feature_parts(rng, feature, body)
    type_name = V.building_type(height, fp[2] - fp[0], fp[3] - fp[1], feature)
    return _building(index, parts, color_name, type_name, feature, shape)


def _trees(rng: np.random.Generator, cfg: CityConfig, parks, blocks) -> list[Tree]:
    """60 % of the trees in parks (if any), the rest along the sidewalks of building blocks."""
    n_park = int(round(0.6 * cfg.n_trees)) if parks else 0
    street_blocks = [b for b in blocks if b.kind == "block"]
    trees = []
    for k in range(cfg.n_trees):
        if k < n_park:
            region = parks[rng.integers(len(parks))]
            x = rng.uniform(region.lo[0] + 4, region.hi[0] - 4)
            y = rng.uniform(region.lo[1] + 4, region.hi[1] - 4)
        elif street_blocks:
            region = street_blocks[rng.integers(len(street_blocks))]
            t, side = rng.uniform(0.05, 0.95), rng.integers(4)
            inset = cfg.sidewalk_m / 2
            xs = (region.lo[0] + inset, region.hi[0] - inset)
            ys = (region.lo[1] + inset, region.hi[1] - inset)
            if side < 2:
                x, y = xs[0] + t * (xs[1] - xs[0]), ys[side]
            else:
                x, y = xs[side - 2], ys[0] + t * (ys[1] - ys[0])
        else:
            break
        height = rng.uniform(6.0, 14.0)
        canopy = rng.uniform(0.6, 1.0) * cfg.sidewalk_m if k >= n_park else rng.uniform(4.0, 8.0)
        color = V.CANOPY_COLORS[rng.integers(len(V.CANOPY_COLORS))]
        trees.append(Tree(float(x), float(y), float(height), tuple(tree_parts(x, y, height, canopy, color))))
    return trees


def generate_city(seed: int, cfg: CityConfig | None = None) -> City:
    """The city of `seed`: identical for identical (seed, cfg), different for different seeds."""
    cfg = cfg or CityConfig()
    if int(seed) < 0:
        raise ValueError(f"city seed must be >= 0, got {seed}")
    rng = np.random.default_rng([int(seed), 0xC17])
    layout = make_layout(
        rng, cfg.size_m, cfg.block_m, cfg.road_m, cfg.sidewalk_m, cfg.park_fraction, cfg.water_fraction,
        cfg.n_buildings,
    )  # fmt: skip
    n_towers = min(len(layout.lots), max(1, int(round(cfg.tower_fraction * len(layout.lots)))))
    # Towers go on the roomiest lots; the first one is the city's landmark tower (200-250 m).
    by_room = np.argsort([-lot.min_side for lot in layout.lots], kind="stable")
    tower_lots = rng.permutation(by_room[: max(n_towers, min(len(by_room), 3 * n_towers))])[:n_towers]
    tower_heights = {int(k): rng.uniform(100.0, 200.0) for k in tower_lots}
    tower_heights[int(tower_lots[0])] = rng.uniform(200.0, 250.0)
    buildings = [_random_building(rng, i, lot, tower_heights.get(i)) for i, lot in enumerate(layout.lots)]
    trees = _trees(rng, cfg, layout.parks, layout.blocks)
    half = cfg.size_m / 2
    city = City(
        scene_id=scene_id_of(seed),
        bounds=SceneBounds(-half, half, -half, half, 0.0, cfg.max_altitude_m),
        buildings=tuple(buildings),
        trees=tuple(trees),
        roads=tuple(layout.roads),
        parks=tuple(layout.parks),
        water=tuple(layout.water),
        plazas=tuple(layout.plazas),
        blocks=tuple(layout.blocks),
        seed=int(seed),
        config=cfg,
    )
    top = max(float(b.hi[2]) for b in buildings)
    if top > cfg.max_altitude_m:  # guards the feature sizes in city_buildings against the flying volume
        raise RuntimeError(f"building top {top:.1f} m exceeds max_altitude_m {cfg.max_altitude_m}")
    return city
