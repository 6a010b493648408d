"""UnrealCV bridge (the UE5 scenes): TCP framing plus the `vset` / `vget` camera commands.

Wire format (unrealcv client 0.4-1.x): each message is uint32 magic 0x9E2B83C1, uint32 payload size
(little-endian), payload. Requests are `"<id>:<command>"`, replies `"<id>:<body>"`; the server greets
every new connection with `"connected to <project>"`. Poses follow the official eval: centimetres,
left-handed (y negated), rotation `pitch -yaw roll` in degrees, set on cameras 0 and 1.
"""

from __future__ import annotations

import math
import re
import socket
import struct
from dataclasses import dataclass

import cv2
import numpy as np

from openfly_agent.sim.bridges.base import (
    BridgeConfig,
    BridgeError,
    EngineBridge,
    WireError,
    bgr_to_rgb,
    format_number,
    open_socket,
    recv_exact,
)
from openfly_agent.sim.occupancy import OccupancyGrid
from openfly_agent.utils.geometry import Pose

MAGIC = 0x9E2B83C1
HEADER = struct.Struct("<II")  # magic, payload size
CM_PER_M = 100.0
_REPLY = re.compile(rb"^(\d{1,8}):", re.DOTALL)


@dataclass
class UnrealCVConfig(BridgeConfig):
    """UnrealCV server settings (`Port=` in the scene's unrealcv.ini; the official eval picks 9000-9100).

    Attributes:
        pose_cameras: cameras that receive every pose (the official eval moves both 0 and 1).
        image_camera: camera whose `lit` image is read (1, spawned at start-up).
        width, height: size set on `image_camera` at connect time (0 leaves the engine's setting).
        spawn_camera: send `vset /cameras/spawn` at connect time, as the official eval does.
    """

    pose_cameras: tuple[int, ...] = (0, 1)
    image_camera: int = 1
    width: int = 1920
    height: int = 1080
    spawn_camera: bool = True

    def __post_init__(self) -> None:
        super().__post_init__()
        if not self.pose_cameras:
            raise ValueError("UnrealCVConfig.pose_cameras must name at least one camera id")
        if self.width < 0 or self.height < 0 or (self.width == 0) != (self.height == 0):
            raise ValueError(
                f"UnrealCVConfig width/height must both be > 0 (or both 0), got {self.width}x{self.height}"
            )


def unrealcv_location(pose: Pose) -> tuple[float, float, float]:
    """World metres (z up, right-handed) -> UE centimetres (left-handed): (x*100, -y*100, z*100)."""
    return (pose.x * CM_PER_M, -pose.y * CM_PER_M, pose.z * CM_PER_M)


def unrealcv_rotation(pose: Pose, pitch_deg: float, roll_deg: float = 0.0) -> tuple[float, float, float]:
    """(pitch, yaw, roll) in UE degrees: yaw is negated (UE yaw turns clockwise seen from above)."""
    return (pitch_deg, -math.degrees(pose.yaw), roll_deg)


def unrealcv_pose_commands(pose: Pose, pitch_deg: float, cameras: tuple[int, ...] = (0, 1)) -> list[str]:
    """The `vset` commands of one pose, in the official order: every location, then every rotation."""
    location = " ".join(format_number(v) for v in unrealcv_location(pose))
    rotation = " ".join(format_number(v) for v in unrealcv_rotation(pose, pitch_deg))
    return [f"vset /camera/{c}/location {location}" for c in cameras] + [
        f"vset /camera/{c}/rotation {rotation}" for c in cameras
    ]


def pack_message(payload: bytes) -> bytes:
    """One framed message: magic, size, payload."""
    return HEADER.pack(MAGIC, len(payload)) + payload


def read_message(sock: socket.socket) -> bytes:
    """Read one framed message and return its payload."""
    magic, size = HEADER.unpack(recv_exact(sock, HEADER.size))
    if magic != MAGIC:
        raise WireError(f"bad UnrealCV magic 0x{magic:08X} (expected 0x{MAGIC:08X}); stream out of sync")
    return recv_exact(sock, size)


class UnrealCVBridge(EngineBridge):
    """`Simulator` over an UnrealCV server. Frames: `vget /camera/<i>/lit png` decoded to RGB.

    Landmark boxes are not available (`Observation.boxes` is None).
    """

    engine = "unrealcv"
    default_port = 9000

    def __init__(self, config: UnrealCVConfig | None = None, occupancy: OccupancyGrid | None = None):
        super().__init__(config or UnrealCVConfig(), occupancy)
        self.config: UnrealCVConfig
        self._sock: socket.socket | None = None
        self._next_id = 0

    def _open(self) -> None:
        host, port = self.address
        self._sock = open_socket(host, port, self.config.connect_timeout_s, self.config.read_timeout_s)
        self._sock.settimeout(self.config.connect_timeout_s)
        greeting = read_message(self._sock)
        if not greeting.startswith(b"connected"):
            raise WireError(f"UnrealCV server did not confirm the connection: {greeting[:200]!r}")
        self._sock.settimeout(self.config.read_timeout_s)
        self._next_id = 0
        cfg = self.config
        if cfg.spawn_camera:
            self._checked("vset /cameras/spawn")
        if cfg.width:
            self._checked(f"vset /camera/{cfg.image_camera}/size {cfg.width} {cfg.height}")

    def _close_transport(self) -> None:
        if self._sock is not None:
            sock, self._sock = self._sock, None
            sock.close()

    def request(self, command: str) -> bytes:
        """Send one command and return the reply body (text or binary)."""
        if self._sock is None:
            raise WireError("not connected")
        message_id = self._next_id
        self._next_id += 1
        self._sock.sendall(pack_message(f"{message_id}:{command}".encode()))
        reply = read_message(self._sock)
        match = _REPLY.match(reply)
        if match is None or int(match.group(1)) != message_id:
            raise WireError(f"reply to {command!r} does not carry id {message_id}: {reply[:80]!r}")
        return reply[match.end() :]

    def _checked(self, command: str) -> bytes:
        body = self.request(command)
        if body[:5].lower() == b"error":
            raise BridgeError(
                f"UnrealCV at {self.address[0]}:{self.address[1]} rejected {command!r}: "
                f"{body.decode(errors='replace')}"
            )
        return body

    def _render(self, pose: Pose, pitch_deg: float, scene_id: str) -> np.ndarray:
        for command in unrealcv_pose_commands(pose, pitch_deg, self.config.pose_cameras):
            self._checked(command)
        command = f"vget /camera/{self.config.image_camera}/lit png"
        png = self._checked(command)
        frame = cv2.imdecode(np.frombuffer(png, dtype=np.uint8), cv2.IMREAD_COLOR)  # BGR
        if frame is None:
            raise BridgeError(
                f"UnrealCV reply to {command!r} is not a PNG image ({len(png)} bytes: {png[:40]!r})"
            )
        return bgr_to_rgb(frame)
