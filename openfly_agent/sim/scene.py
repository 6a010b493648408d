"""Scene and landmark types shared by the embedded city, real scene readers and the toolchain."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass(frozen=True)
class Landmark:
    """A named object an instruction can refer to (a building, tower, ...).

    Positions are in the world frame of docs/CONVENTIONS.md (metres, z up). `extent` is the full size
    (dx, dy, dz) of its axis-aligned bounding box, `position` the centre of its footprint at roof height
    for real landmark lists (z = top), or the box centre for embedded buildings (see `center`).
    """

    landmark_id: str
    type: str  # building, skyscraper, tower, house, ...
    color: str
    size: str  # low-rise, mid-rise, high-rise, ...
    shape: str  # rectangular, cylindrical, L-shaped, ...
    feature: str  # rooftop billboard, spire, dome, ...
    position: tuple[float, float, float]  # (x, y, z) metres
    extent: tuple[float, float, float] = (0.0, 0.0, 0.0)  # (dx, dy, dz) metres; zeros when unknown
    attributes: dict = field(default_factory=dict)

    def description(self) -> str:
        """A short noun phrase, e.g. 'tall beige tower with a spire'."""
        parts = [p for p in (self.color, self.type) if p and p != "test"]
        text = " ".join(parts) if parts else "building"
        if self.feature and self.feature not in ("test", "none", ""):
            text += f" with a {self.feature}"
        return text


@dataclass(frozen=True)
class SceneBounds:
    """[xmin, xmax, ymin, ymax, zmin, zmax] in metres, as `MapBound` of the official env_*.yaml."""

    xmin: float
    xmax: float
    ymin: float
    ymax: float
    zmin: float
    zmax: float

    def as_list(self) -> list[float]:
        return [self.xmin, self.xmax, self.ymin, self.ymax, self.zmin, self.zmax]

    def contains(self, points: np.ndarray) -> np.ndarray:
        """(N, 3) -> (N,) bool."""
        p = np.atleast_2d(points)
        return (
            (p[:, 0] >= self.xmin)
            & (p[:, 0] <= self.xmax)
            & (p[:, 1] >= self.ymin)
            & (p[:, 1] <= self.ymax)
            & (p[:, 2] >= self.zmin)
            & (p[:, 2] <= self.zmax)
        )
