"""Pinhole camera of the embedded renderer: axes from (yaw, pitch), projection to pixels, GL matrices.

World frame of docs/CONVENTIONS.md (x east, y north, z up). The camera sits at the drone position and looks along
the heading yaw, tilted by pitch (negative = down); no roll. Pixels: u to the right, v down, pixel (i, j)
covers [i, i + 1) x [j, j + 1), the principal point is the image centre, square pixels.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from openfly_agent.utils.geometry import Pose


@dataclass(frozen=True)
class CameraModel:
    """Image size and horizontal field of view; focal length follows (fx = fy = W / 2 / tan(HFOV / 2))."""

    width: int
    height: int
    hfov_deg: float = 90.0

    def __post_init__(self) -> None:
        if self.width < 1 or self.height < 1:
            raise ValueError(f"image size must be positive, got {self.width} x {self.height}")
        if not 1.0 <= self.hfov_deg <= 170.0:
            raise ValueError(f"hfov_deg must lie in [1, 170], got {self.hfov_deg}")

    @property
    def focal_px(self) -> float:
        return self.width / 2.0 / math.tan(math.radians(self.hfov_deg) / 2.0)


def camera_axes(yaw: float, pitch_deg: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(forward, right, up) unit vectors (3,) in the world frame."""
    pitch = math.radians(pitch_deg)
    cy, sy, cp, sp = math.cos(yaw), math.sin(yaw), math.cos(pitch), math.sin(pitch)
    forward = np.array([cy * cp, sy * cp, sp])
    right = np.array([sy, -cy, 0.0])
    up = np.array([-cy * sp, -sy * sp, cp])  # right x forward
    return forward, right, up


def project(
    points: np.ndarray, pose: Pose, pitch_deg: float, camera: CameraModel
) -> tuple[np.ndarray, np.ndarray]:
    """World points (N, 3) -> pixel coordinates (N, 2) (u right, v down) and depth along the view axis (N,).

    Points behind the camera get depth <= 0 (their pixel coordinates are meaningless).
    """
    forward, right, up = camera_axes(pose.yaw, pitch_deg)
    d = np.atleast_2d(points) - pose.position  # (N, 3)
    depth = d @ forward
    f = camera.focal_px
    with np.errstate(divide="ignore", invalid="ignore"):
        u = camera.width / 2.0 + f * (d @ right) / depth
        v = camera.height / 2.0 - f * (d @ up) / depth
    return np.stack([u, v], axis=1), depth


def view_matrix(pose: Pose, pitch_deg: float) -> np.ndarray:
    """(4, 4) world -> GL eye coordinates (x right, y up, looking down -z)."""
    forward, right, up = camera_axes(pose.yaw, pitch_deg)
    rot = np.stack([right, up, -forward])  # (3, 3)
    view = np.eye(4)
    view[:3, :3] = rot
    view[:3, 3] = -rot @ pose.position
    return view


def projection_matrix(camera: CameraModel, near: float, far: float, flip_y: bool = True) -> np.ndarray:
    """(4, 4) GL perspective matching `project`; `flip_y` puts image row 0 (the top) first in memory."""
    proj = np.zeros((4, 4))
    proj[0, 0] = camera.focal_px / (camera.width / 2.0)
    proj[1, 1] = camera.focal_px / (camera.height / 2.0) * (-1.0 if flip_y else 1.0)
    proj[2, 2] = -(far + near) / (far - near)
    proj[2, 3] = -2.0 * far * near / (far - near)
    proj[3, 2] = -1.0
    return proj


def frustum_planes(view_proj: np.ndarray) -> np.ndarray:
    """(6, 4) planes (a, b, c, d), normals unit and pointing inwards: inside iff a x + b y + c z + d >= 0."""
    m = view_proj
    planes = np.stack([m[3] + m[0], m[3] - m[0], m[3] + m[1], m[3] - m[1], m[3] + m[2], m[3] - m[2]])
    return planes / np.linalg.norm(planes[:, :3], axis=1, keepdims=True)


def linear_depth(ndc_depth: np.ndarray, near: float, far: float) -> np.ndarray:
    """Window depth in [0, 1] (GL default range) -> metres along the view axis; 1.0 (nothing drawn) -> inf."""
    z = 2.0 * ndc_depth.astype(np.float64) - 1.0
    with np.errstate(divide="ignore"):
        metres = 2.0 * near * far / (far + near - z * (far - near))
    return np.where(ndc_depth >= 1.0, np.inf, metres).astype(np.float32)
