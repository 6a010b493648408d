"""AirSim bridge: msgpack-RPC over TCP (`simSetVehiclePose`, `simGetImages`), poses in NED.

msgpack-RPC: a request is `[0, msgid, method, params]`, a reply `[1, msgid, error, result]`, back to
back on one TCP stream. AirSim structs travel as maps (`Vector3r` -> {x_val, y_val, z_val}). The pose
conversion is the official one: `Vector3r(x, -y, -z)` and `to_quaternion(pitch, 0, -yaw)`.
Needs the `msgpack` package (`pip install 'openfly-agent[bridges]'`), imported on first connect.
"""

from __future__ import annotations

import math
import socket
import time
from dataclasses import dataclass

import cv2
import numpy as np

from openfly_agent.sim.bridges.base import (
    BridgeConfig,
    BridgeError,
    EngineBridge,
    WireError,
    bgr_to_rgb,
    open_socket,
    time_left,
)
from openfly_agent.sim.occupancy import OccupancyGrid
from openfly_agent.utils.geometry import Pose
from openfly_agent.utils.imports import require_package

IMAGE_TYPE_SCENE = 0
DRIVETRAIN_MAX_DEGREE_OF_FREEDOM = 0
_REQUEST, _RESPONSE = 0, 1


@dataclass
class AirSimConfig(BridgeConfig):
    """AirSim RPC settings (port 41451 unless `ApiServerPort` is set in settings.json).

    Attributes:
        vehicle_name: "" addresses the default vehicle, as the official eval does.
        camera_name: the OpenFly scenes define `front_custom` (1920x1080, FOV 90).
        enable_api_control: send `enableApiControl(True)` and `armDisarm(True)` after connecting.
        hover_before_pose: send a zero-velocity `moveByVelocityBodyFrame(0, 0, 0, 0.02)` before each
            pose, as the official eval does, so the drone does not drift between teleports.
    """

    vehicle_name: str = ""
    camera_name: str = "front_custom"
    enable_api_control: bool = True
    hover_before_pose: bool = True


def to_quaternion(pitch: float, roll: float, yaw: float) -> tuple[float, float, float, float]:
    """AirSim's Euler (radians) -> quaternion (w, x, y, z), the formula of `airsim.to_quaternion`."""
    cy, sy = math.cos(yaw * 0.5), math.sin(yaw * 0.5)
    cr, sr = math.cos(roll * 0.5), math.sin(roll * 0.5)
    cp, sp = math.cos(pitch * 0.5), math.sin(pitch * 0.5)
    return (
        cy * cr * cp + sy * sr * sp,
        cy * sr * cp - sy * cr * sp,
        cy * cr * sp + sy * sr * cp,
        sy * cr * cp - cy * sr * sp,
    )


def airsim_pose(pose: Pose, pitch_deg: float) -> dict:
    """World pose -> the msgpack map of an AirSim `Pose` in NED: (x, -y, -z), quaternion(pitch, 0, -yaw)."""
    w, x, y, z = to_quaternion(math.radians(pitch_deg), 0.0, -pose.yaw)
    return {
        "position": {"x_val": float(pose.x), "y_val": float(-pose.y), "z_val": float(-pose.z)},
        "orientation": {"w_val": w, "x_val": x, "y_val": y, "z_val": z},
    }


def decode_image_response(response: dict, camera_name: str) -> np.ndarray:
    """An uncompressed `ImageResponse` map -> (H, W, 3) uint8 RGB.

    AirSim sends the raw pixels in BGR order (the official toolchain writes them with cv2.imwrite);
    some older servers send 4 channels (BGRA).
    """
    width, height = int(response.get("width", 0)), int(response.get("height", 0))
    data = response.get("image_data_uint8", b"")
    pixels = np.frombuffer(bytes(data), dtype=np.uint8)
    if width <= 0 or height <= 0 or pixels.size == 0:
        raise BridgeError(
            f"AirSim returned an empty image for camera {camera_name!r} "
            f"(message: {response.get('message', '')!r}); "
            "check camera_name / vehicle_name against settings.json"
        )
    channels = pixels.size // (width * height)
    if channels not in (3, 4) or pixels.size != width * height * channels:
        raise BridgeError(
            f"AirSim image of {pixels.size} bytes does not fit {width}x{height} with 3 or 4 channels"
        )
    frame = pixels.reshape(height, width, channels)
    if channels == 4:
        return cv2.cvtColor(frame, cv2.COLOR_BGRA2RGB)
    return bgr_to_rgb(frame)


class MsgpackRpcConnection:
    """A minimal synchronous msgpack-RPC client on one socket."""

    def __init__(self, sock: socket.socket, msgpack_module, read_timeout_s: float):
        self._sock = sock
        self._read_timeout_s = read_timeout_s
        self._msgpack = msgpack_module
        self._unpacker = msgpack_module.Unpacker(raw=False, max_buffer_size=512 * 1024 * 1024)
        self._next_id = 0

    def call(self, method: str, *params):
        """Send `method(*params)`, wait for its reply; engine errors raise `BridgeError`."""
        msgid = self._next_id
        self._next_id += 1
        self._sock.sendall(self._msgpack.packb([_REQUEST, msgid, method, list(params)], use_bin_type=True))
        deadline = time.monotonic() + self._read_timeout_s  # for the whole reply, however it is split
        while True:
            for message in self._unpacker:
                if not isinstance(message, (list, tuple)) or len(message) != 4 or message[0] != _RESPONSE:
                    raise WireError(
                        f"unexpected msgpack-RPC message while waiting for {method}: {message!r:.200}"
                    )
                if message[1] != msgid:
                    raise WireError(f"reply id {message[1]} while waiting for {method} (id {msgid})")
                if message[2] is not None:
                    raise BridgeError(f"AirSim {method} failed: {message[2]!r}")
                return message[3]
            self._sock.settimeout(time_left(deadline, f"the reply to {method}"))
            data = self._sock.recv(1 << 20)
            if not data:
                raise EOFError(f"AirSim closed the connection while waiting for {method}")
            self._unpacker.feed(data)

    def close(self) -> None:
        self._sock.close()


class AirSimBridge(EngineBridge):
    """`Simulator` over an AirSim RPC server (no `airsim` package needed). Boxes are None."""

    engine = "airsim"
    default_port = 41451

    def __init__(self, config: AirSimConfig | None = None, occupancy: OccupancyGrid | None = None):
        super().__init__(config or AirSimConfig(), occupancy)
        self.config: AirSimConfig
        self._rpc: MsgpackRpcConnection | None = None

    def _open(self) -> None:
        msgpack = require_package("msgpack", extra="bridges")
        host, port = self.address
        sock = open_socket(host, port, self.config.connect_timeout_s, self.config.read_timeout_s)
        self._rpc = MsgpackRpcConnection(sock, msgpack, self.config.read_timeout_s)
        if not self._rpc.call("ping"):
            raise WireError("AirSim ping returned false")
        if self.config.enable_api_control:
            self._rpc.call("enableApiControl", True, self.config.vehicle_name)
            self._rpc.call("armDisarm", True, self.config.vehicle_name)

    def _close_transport(self) -> None:
        if self._rpc is not None:
            rpc, self._rpc = self._rpc, None
            rpc.close()

    def _render(self, pose: Pose, pitch_deg: float, scene_id: str) -> np.ndarray:
        if self._rpc is None:
            raise WireError("not connected")
        vehicle = self.config.vehicle_name
        if self.config.hover_before_pose:
            yaw_mode = {"is_rate": True, "yaw_or_rate": 0.0}
            self._rpc.call(
                "moveByVelocityBodyFrame",
                0.0,
                0.0,
                0.0,
                0.02,
                DRIVETRAIN_MAX_DEGREE_OF_FREEDOM,
                yaw_mode,
                vehicle,
            )
        self._rpc.call("simSetVehiclePose", airsim_pose(pose, pitch_deg), True, vehicle)
        request = {
            "camera_name": self.config.camera_name,
            "image_type": IMAGE_TYPE_SCENE,
            "pixels_as_float": False,
            "compress": False,
        }
        responses = self._rpc.call("simGetImages", [request], vehicle, False)
        if not responses:
            raise BridgeError(f"AirSim simGetImages returned no image for camera {self.config.camera_name!r}")
        return decode_image_response(responses[0], self.config.camera_name)
