"""Hand-built scenes and hand-computed expectations shared by the simulator tests."""

import math

import numpy as np

from openfly_agent.sim.camera import CameraModel, project
from openfly_agent.sim.city import City, make_box_building
from openfly_agent.sim.scene import SceneBounds
from openfly_agent.utils.geometry import Pose

# A red 20 x 20 x 100 m tower whose west face (x = 90) looks at the origin.
TOWER_LO, TOWER_HI = (90.0, -10.0, 0.0), (110.0, 10.0, 100.0)


def tower_city(*extra) -> City:
    """The tower (index 0, id 'b0000') plus `extra` buildings, in a 400 m scene with no ground regions."""
    buildings = [make_box_building(0, TOWER_LO, TOWER_HI, color="red")]
    buildings += [make_box_building(i + 1, lo, hi, color="blue") for i, (lo, hi) in enumerate(extra)]
    return City("test-tower", SceneBounds(-200, 200, -200, 200, 0, 150), tuple(buildings))


def pixel_box(corners: np.ndarray, pose: Pose, camera: CameraModel, pitch_deg: float = 0.0) -> np.ndarray:
    """Expected instance-buffer box of a face seen head-on: pixels whose centre lies inside its projection.

    `corners` (4, 3) of an axis-aligned rectangle; returns (cx, cy, w, h) normalised.
    """
    uv, depth = project(corners, pose, pitch_deg, camera)
    assert (depth > 0).all()
    u0, u1, v0, v1 = uv[:, 0].min(), uv[:, 0].max(), uv[:, 1].min(), uv[:, 1].max()
    i0, i1 = math.ceil(u0 - 0.5), math.ceil(u1 - 0.5) - 1  # centres i + 0.5 in [u0, u1)
    j0, j1 = math.ceil(v0 - 0.5), math.ceil(v1 - 0.5) - 1
    w, h = camera.width, camera.height
    return np.array([(i0 + i1 + 1) / 2 / w, (j0 + j1 + 1) / 2 / h, (i1 + 1 - i0) / w, (j1 + 1 - j0) / h])


def west_face(lo, hi, top=None) -> np.ndarray:
    """(4, 3) corners of the x = lo[0] face of a box (optionally cut at height `top`)."""
    z1 = hi[2] if top is None else top
    return np.array([[lo[0], lo[1], lo[2]], [lo[0], hi[1], lo[2]], [lo[0], lo[1], z1], [lo[0], hi[1], z1]])


def assert_same_frame(a, b, max_changed: float = 0.005) -> None:
    """Frames of one view rendered in different batch slots: llvmpipe rasterises at a different framebuffer
    offset, so a few edge pixels may differ; everything else must be equal and boxes agree within a pixel."""
    changed = np.any(a.rgb != b.rgb, axis=-1).mean()
    assert changed <= max_changed, f"{changed:.2%} of the pixels differ"
    assert a.boxes.keys() == b.boxes.keys()
    size = np.array(a.rgb.shape[1::-1] * 2, dtype=np.float64)  # (W, H, W, H)
    for key in a.boxes:
        assert np.all(np.abs(a.boxes[key] - b.boxes[key]) * size <= 1.0 + 1e-9), key
