"""Tiny synthetic scenes for the toolchain tests: axis-aligned box buildings sampled as surface points."""

from __future__ import annotations

import numpy as np

from openfly_agent.sim.occupancy import OccupancyGrid
from openfly_agent.sim.scene import Landmark, SceneBounds

BOUNDS = SceneBounds(-150.0, 150.0, -150.0, 150.0, 0.0, 100.0)


def box_surface_points(lo, hi, spacing: float = 1.0) -> np.ndarray:
    """(N, 3) points on the faces of the box [lo, hi] (no bottom face), every `spacing` metres."""
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    axes = [np.append(np.arange(lo[i], hi[i], spacing), hi[i]) for i in range(3)]
    faces = []
    for axis in range(3):
        others = [a for a in range(3) if a != axis]
        u, v = np.meshgrid(axes[others[0]], axes[others[1]], indexing="ij")
        for value in (lo[axis], hi[axis]) if axis != 2 else (hi[axis],):
            face = np.zeros((u.size, 3))
            face[:, axis] = value
            face[:, others[0]], face[:, others[1]] = u.ravel(), v.ravel()
            faces.append(face)
    return np.concatenate(faces)


# (landmark id, lo, hi, colour, type, feature)
BUILDINGS = [
    ("b0", (-20.0, -20.0, 0.0), (20.0, 20.0, 60.0), "red", "tower", "spire"),
    ("b1", (60.0, -90.0, 0.0), (90.0, -60.0, 30.0), "blue", "office building", "rooftop billboard"),
    ("b2", (-100.0, 50.0, 0.0), (-70.0, 80.0, 45.0), "white", "skyscraper", "dome"),
]


def synthetic_scene():
    """(points (N, 3), landmarks, true occupancy at 1 m) of three box buildings on flat ground z = 0."""
    points = np.concatenate([box_surface_points(lo, hi) for _, lo, hi, *_ in BUILDINGS])
    landmarks = []
    truth = OccupancyGrid.empty(BOUNDS, 1.0)
    for lid, lo, hi, color, kind, feature in BUILDINGS:
        lo, hi = np.array(lo), np.array(hi)
        centre, extent = (lo + hi) / 2, hi - lo
        landmarks.append(
            Landmark(lid, kind, color, "mid-rise", "rectangular", feature, tuple(centre), tuple(extent))
        )
        truth.mark_box(lo, hi)
    return points, landmarks, truth
