"""3D Gaussian Splatting bridge: the OpenFly-patched SIBR viewer's HTTP renderer (`POST /render`).

The form carries a COLMAP cameras.txt line (`camera`), a COLMAP images.txt line with the
world-to-camera pose (`image`) and an output directory (`path`); the server renders, **writes** the
image into that directory and replies with text only, so the bridge and the server must share a
filesystem. Poses are divided by the scene's scale ratio first (GS_SCALE_RATIOS).
"""

from __future__ import annotations

import http.client
import math
import shutil
import tempfile
import urllib.parse
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from openfly_agent.sim.bridges.base import BridgeConfig, BridgeError, EngineBridge, bgr_to_rgb, format_number
from openfly_agent.sim.occupancy import OccupancyGrid
from openfly_agent.sim.real_scene import GS_SCALE_RATIOS
from openfly_agent.utils.geometry import Pose

# The official PINHOLE camera: 1436 x 1077, fx = fy = 718.861, principal point (718, 538.5); HFOV ~90 deg.
OFFICIAL_CAMERA_LINE = "0 PINHOLE 1436 1077 718.861 718.861 718 538.5"
OFFICIAL_PITCH_DEG = -40.0  # the official GS bridges force this pitch for every frame
# Body axes (x forward, y left, z up) -> camera axes (x right, y down, z forward).
BODY_TO_CAMERA = np.array([[0.0, -1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]])
_IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")


@dataclass
class GSHttpConfig(BridgeConfig):
    """SIBR HTTP renderer settings (port 18080).

    Attributes:
        camera_line: COLMAP cameras.txt line sent with every request.
        scale_ratio: divide world metres by this before rendering; None uses the episode scene's ratio
            from GS_SCALE_RATIOS (the official eval uses 5.15 for every scene; set 5.15 for parity).
        pitch_override_deg: pitch used for every frame instead of the episode's (the official bridges
            force -40 deg, and the released GS images were taken that way); None uses the episode's.
        output_dir: where the server writes frames (one sub-folder per request); "" = a temporary
            directory removed on close().
        keep_frames: keep the rendered files instead of deleting each one after reading it.
    """

    camera_line: str = OFFICIAL_CAMERA_LINE
    scale_ratio: float | None = None
    pitch_override_deg: float | None = OFFICIAL_PITCH_DEG
    output_dir: str = ""
    keep_frames: bool = False

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.scale_ratio is not None and not self.scale_ratio > 0:
            raise ValueError(f"GSHttpConfig.scale_ratio must be > 0 (or None), got {self.scale_ratio}")
        if len(self.camera_line.split()) < 5:
            raise ValueError(f"GSHttpConfig.camera_line is not a COLMAP camera line: {self.camera_line!r}")


def rotation_x(angle: float) -> np.ndarray:
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def rotation_y(angle: float) -> np.ndarray:
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def rotation_z(angle: float) -> np.ndarray:
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def quaternion_from_matrix(rotation: np.ndarray) -> np.ndarray:
    """(3, 3) rotation -> (4,) unit quaternion (w, x, y, z) with w >= 0 (Shepperd's method)."""
    m = np.asarray(rotation, dtype=np.float64)
    trace = m[0, 0] + m[1, 1] + m[2, 2]
    if trace > 0:
        s = 2.0 * math.sqrt(trace + 1.0)
        q = [0.25 * s, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s]
    elif m[0, 0] > m[1, 1] and m[0, 0] > m[2, 2]:
        s = 2.0 * math.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2])
        q = [(m[2, 1] - m[1, 2]) / s, 0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s]
    elif m[1, 1] > m[2, 2]:
        s = 2.0 * math.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2])
        q = [(m[0, 2] - m[2, 0]) / s, (m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s]
    else:
        s = 2.0 * math.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1])
        q = [(m[1, 0] - m[0, 1]) / s, (m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s]
    quat = np.array(q) / np.linalg.norm(q)
    return -quat if quat[0] < 0 else quat


def sibr_world_to_camera(
    pose: Pose, pitch_deg: float, scale_ratio: float, roll_deg: float = 0.0
) -> tuple[np.ndarray, np.ndarray]:
    """The official GS pose: R = B · Ry(pitch) · Rz(-yaw) · Rx(roll), T = -R · (position / scale).

    Returns:
        (4,) quaternion (w, x, y, z) of R and (3,) translation T: the world-to-camera transform of a
        COLMAP images.txt line, in the scene's own units.
    """
    rotation = (
        BODY_TO_CAMERA
        @ rotation_y(math.radians(pitch_deg))
        @ rotation_z(-pose.yaw)
        @ rotation_x(math.radians(roll_deg))
    )  # (3, 3)
    position = pose.position / scale_ratio  # (3,)
    return quaternion_from_matrix(rotation), -rotation @ position


def sibr_image_line(quaternion: np.ndarray, translation: np.ndarray, name: str = "00000000.png") -> str:
    """COLMAP images.txt line `IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME`, ids 0 as the official bridge."""
    numbers = " ".join(format_number(v) for v in (*quaternion, *translation))
    return f"0 {numbers} 0 {name}"


class GSHttpBridge(EngineBridge):
    """`Simulator` over the SIBR HTTP renderer; frames are read back from the output directory."""

    engine = "gs_http"
    default_port = 18080

    def __init__(self, config: GSHttpConfig | None = None, occupancy: OccupancyGrid | None = None):
        super().__init__(config or GSHttpConfig(), occupancy)
        self.config: GSHttpConfig
        self._output_dir: Path | None = None
        self._owns_output_dir = False
        self._frame_index = 0

    def scale_for(self, scene_id: str) -> float:
        """The world-metres -> scene-units divisor of `scene_id`."""
        if self.config.scale_ratio is not None:
            return self.config.scale_ratio
        if scene_id not in GS_SCALE_RATIOS:
            raise BridgeError(
                f"no scale ratio for 3DGS scene {scene_id!r} (known: {sorted(GS_SCALE_RATIOS)}); "
                "set GSHttpConfig.scale_ratio"
            )
        return GS_SCALE_RATIOS[scene_id]

    def _request(self, method: str, path: str, body: bytes | None = None, headers: dict | None = None):
        host, port = self.address
        connection = http.client.HTTPConnection(host, port, timeout=self.config.connect_timeout_s)
        try:
            connection.connect()
            connection.sock.settimeout(self.config.read_timeout_s)
            connection.request(method, path, body=body, headers=headers or {})
            response = connection.getresponse()
            return response.status, response.read().decode("utf-8", errors="replace")
        finally:
            connection.close()

    def _open(self) -> None:
        status, text = self._request("GET", "/")
        if status != 200:
            raise BridgeError(
                f"SIBR renderer at {self.address[0]}:{self.address[1]} answered GET / with {status}: "
                f"{text[:200]}"
            )
        if self._output_dir is None:
            if self.config.output_dir:
                self._output_dir = Path(self.config.output_dir)
                self._output_dir.mkdir(parents=True, exist_ok=True)
            else:
                self._output_dir = Path(tempfile.mkdtemp(prefix="openfly_sibr_"))
                self._owns_output_dir = True

    def _close_transport(self) -> None:
        """HTTP connections are per request; nothing stays open."""

    def close(self) -> None:
        super().close()
        if self._owns_output_dir and self._output_dir is not None:
            shutil.rmtree(self._output_dir, ignore_errors=True)
            self._output_dir, self._owns_output_dir = None, False

    def _render(self, pose: Pose, pitch_deg: float, scene_id: str) -> np.ndarray:
        assert self._output_dir is not None  # set by _open
        pitch = self.config.pitch_override_deg if self.config.pitch_override_deg is not None else pitch_deg
        quaternion, translation = sibr_world_to_camera(pose, pitch, self.scale_for(scene_id))
        frame_dir = self._output_dir / f"{self._frame_index:08d}"
        self._frame_index += 1
        frame_dir.mkdir(parents=True, exist_ok=True)
        form = {
            "camera": self.config.camera_line,
            "image": sibr_image_line(quaternion, translation),
            "path": f"{frame_dir}/",
        }
        body = urllib.parse.urlencode(form).encode()
        headers = {"Content-Type": "application/x-www-form-urlencoded"}
        status, text = self._request("POST", "/render", body, headers)
        if status != 200:
            raise BridgeError(f"SIBR /render answered {status}: {text[:200]}")
        return self._read_frame(frame_dir)

    def _read_frame(self, frame_dir: Path) -> np.ndarray:
        images = sorted(
            (p for p in frame_dir.iterdir() if p.suffix.lower() in _IMAGE_SUFFIXES),
            key=lambda p: p.stat().st_mtime,
        )
        if not images:
            raise BridgeError(
                f"SIBR /render succeeded but wrote no image into {frame_dir}; "
                "the bridge and the renderer must share a filesystem"
            )
        frame = cv2.imread(str(images[-1]), cv2.IMREAD_COLOR)  # (H, W, 3) BGR
        if frame is None:
            raise BridgeError(f"could not read the rendered image {images[-1]}")
        if not self.config.keep_frames:
            shutil.rmtree(frame_dir, ignore_errors=True)
        return bgr_to_rgb(frame)
