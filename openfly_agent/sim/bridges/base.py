"""What every engine bridge shares: connection settings, reconnect-once, and the episode bookkeeping.

A bridge never integrates motion itself: poses come from `sim/dynamics.py`, the engine only renders
them (teleport, as in the official evaluation). Engines report no collisions; pass an
`OccupancyGrid` of the scene to get `StepInfo.collided` from the swept segment.
"""

from __future__ import annotations

import logging
import socket
import time
from abc import ABC, abstractmethod
from collections.abc import Callable
from dataclasses import dataclass
from typing import ClassVar, TypeVar

import numpy as np

from openfly_agent import constants as C
from openfly_agent.sim.base import EpisodeSpec, Observation, StepInfo
from openfly_agent.sim.dynamics import step_motion
from openfly_agent.sim.occupancy import OccupancyGrid
from openfly_agent.utils.geometry import Pose, wrap_yaw

logger = logging.getLogger(__name__)
T = TypeVar("T")


class BridgeError(RuntimeError):
    """The engine could not be reached, or it refused a command; the message says which and where."""


class WireError(Exception):
    """A malformed or unexpected message on the wire (the connection is dropped and retried once)."""


# Errors after which the connection is dropped and re-opened once.
TRANSPORT_ERRORS = (OSError, EOFError, WireError)


@dataclass
class BridgeConfig:
    """Where the engine listens and how long to wait for it.

    Attributes:
        host: engine address; loopback by default (nothing leaves the machine unless asked).
        port: TCP port; 0 picks the engine's default (UnrealCV 9000, AirSim 41451, SIBR 18080).
        connect_timeout_s: seconds to wait for the TCP connection (and handshake).
        read_timeout_s: seconds to wait for any single reply (frames at 1080p can take a while).
        reconnect: after a dropped connection or a timeout, reconnect once and retry the operation;
            a second failure raises `BridgeError`.
    """

    host: str = "127.0.0.1"
    port: int = 0
    connect_timeout_s: float = 10.0
    read_timeout_s: float = 60.0
    reconnect: bool = True

    def __post_init__(self) -> None:
        if not self.host:
            raise ValueError("BridgeConfig.host must be a host name or address, e.g. 127.0.0.1")
        if not 0 <= self.port <= 65535:
            raise ValueError(f"BridgeConfig.port must be in 0..65535 (0 = engine default), got {self.port}")
        if not (self.connect_timeout_s > 0 and self.read_timeout_s > 0):
            raise ValueError(
                "BridgeConfig.connect_timeout_s and read_timeout_s must be > 0 seconds, got "
                f"{self.connect_timeout_s} and {self.read_timeout_s}"
            )


def time_left(deadline: float, what: str) -> float:
    """Seconds until `deadline` (time.monotonic); TimeoutError once it has passed."""
    left = deadline - time.monotonic()
    if left <= 0:
        raise TimeoutError(f"timed out waiting for {what}")
    return left


def recv_exact(sock: socket.socket, size: int) -> bytes:
    """Read exactly `size` bytes within the socket's timeout in total; EOFError if the peer closes first."""
    timeout = sock.gettimeout()
    deadline = time.monotonic() + (timeout if timeout is not None else 3600.0)
    chunks, remaining = [], size
    try:
        while remaining:
            sock.settimeout(time_left(deadline, f"{remaining} of {size} bytes"))
            chunk = sock.recv(min(remaining, 1 << 20))
            if not chunk:
                raise EOFError(f"connection closed with {remaining} of {size} bytes unread")
            chunks.append(chunk)
            remaining -= len(chunk)
    finally:
        sock.settimeout(timeout)
    return b"".join(chunks)


def open_socket(host: str, port: int, connect_timeout_s: float, read_timeout_s: float) -> socket.socket:
    """A connected TCP socket whose later reads time out after `read_timeout_s`."""
    sock = socket.create_connection((host, port), timeout=connect_timeout_s)
    sock.settimeout(read_timeout_s)
    sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
    return sock


def bgr_to_rgb(frame: np.ndarray) -> np.ndarray:
    """(H, W, 3) uint8 BGR (OpenCV order) -> (H, W, 3) uint8 RGB, contiguous."""
    if frame.ndim != 3 or frame.shape[2] != 3:
        raise ValueError(f"expected an (H, W, 3) frame, got shape {frame.shape}")
    return np.ascontiguousarray(frame[:, :, ::-1])


def format_number(value: float) -> str:
    """Shortest round-trip text of a float (Python's `str`, as the official bridges send); no '-0.0'."""
    return repr(float(value) + 0.0)


class EngineBridge(ABC):
    """A `Simulator` backed by an external renderer. Subclasses implement the three transport hooks."""

    engine: ClassVar[str] = "engine"
    default_port: ClassVar[int] = 0

    def __init__(self, config: BridgeConfig, occupancy: OccupancyGrid | None = None):
        self.config = config
        self.occupancy = occupancy
        self._connected = False
        self._episode: EpisodeSpec | None = None
        self._pose: Pose | None = None
        self._last_rgb: np.ndarray | None = None
        self._done = True

    # -- transport hooks -------------------------------------------------------------------------
    @abstractmethod
    def _open(self) -> None:
        """Connect, handshake and initialise the engine (camera size, ...)."""

    @abstractmethod
    def _close_transport(self) -> None:
        """Drop the connection; must not raise."""

    @abstractmethod
    def _render(self, pose: Pose, pitch_deg: float, scene_id: str) -> np.ndarray:
        """Teleport the camera to `pose` and return the frame, (H, W, 3) uint8 RGB."""

    # -- connection handling ---------------------------------------------------------------------
    @property
    def address(self) -> tuple[str, int]:
        return self.config.host, self.config.port or self.default_port

    def _drop(self) -> None:
        self._connected = False
        try:
            self._close_transport()
        except Exception:  # closing a broken connection must not mask the original error
            logger.debug("error while closing %s connection", self.engine, exc_info=True)

    def _call(self, operation: str, action: Callable[[], T]) -> T:
        """Run `action` on a live connection; on a transport error reconnect once, then give up."""
        attempts = 2 if self.config.reconnect else 1
        last_error: BaseException | None = None
        for attempt in range(attempts):
            try:
                if not self._connected:
                    self._open()
                    self._connected = True
                return action()
            except TRANSPORT_ERRORS as err:
                last_error = err
                self._drop()
                if attempt + 1 < attempts:
                    logger.warning(
                        "%s at %s:%d: %s failed (%s); reconnecting once",
                        self.engine,
                        *self.address,
                        operation,
                        err,
                    )
        host, port = self.address
        tried = "after one reconnect" if self.config.reconnect else "(reconnect disabled)"
        raise BridgeError(
            f"{self.engine} at {host}:{port}: {operation} failed {tried}: {type(last_error).__name__}: "
            f"{last_error}. Is the engine running and listening on that host and port?"
        ) from last_error

    def connect(self) -> None:
        """Open the connection now (handshake included), so an engine that cannot be reached fails before
        the first episode; raises `BridgeError` naming the engine, host and port."""
        self._call("connect", lambda: None)

    # -- Simulator protocol ----------------------------------------------------------------------
    def reset(self, episode: EpisodeSpec) -> Observation:
        """Teleport to the episode's start and return the first frame."""
        start = episode.start
        pose = Pose(start.x, start.y, start.z, wrap_yaw(start.yaw))  # annotation yaws are not wrapped
        rgb = self._call("reset", lambda: self._render(pose, episode.pitch_deg, episode.scene_id))
        self._episode, self._pose, self._last_rgb, self._done = episode, pose, rgb, False
        return Observation(rgb=rgb, pose=pose)

    def step(self, action_id: int) -> tuple[Observation, StepInfo]:
        """Execute one action: the pose comes from `sim.dynamics`; STOP ends without an engine call."""
        if self._episode is None or self._pose is None or self._last_rgb is None:
            raise RuntimeError(f"{type(self).__name__}.step() called before reset()")
        if self._done:
            raise RuntimeError(f"{type(self).__name__}.step(): episode {self._episode.episode_id} is over")
        motion = step_motion(self._pose, int(action_id))
        collided = False
        if self.occupancy is not None and not motion.is_stop:
            collided = bool(self.occupancy.segment_collides(motion.start.position, motion.end.position))
        if motion.is_stop:
            self._done = True
        else:
            episode = self._episode
            self._last_rgb = self._call(
                f"step {C.ACTION_NAMES.get(int(action_id), action_id)}",
                lambda: self._render(motion.end, episode.pitch_deg, episode.scene_id),
            )
        self._pose = motion.end
        info = StepInfo(
            action=int(action_id), collided=collided, done=self._done, extra={"engine": self.engine}
        )
        return Observation(rgb=self._last_rgb, pose=self._pose), info

    def close(self) -> None:
        """Drop the connection (a later reset reconnects)."""
        self._drop()

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()
