"""Loopback fake engines for the bridge tests: UnrealCV framing, AirSim msgpack-RPC, SIBR HTTP.

Each server binds 127.0.0.1 on an ephemeral port, runs in one daemon thread, records what it
receives, and stops within a bounded time. They implement the wire formats independently of the
package code, so a framing bug on one side cannot hide itself.
"""

from __future__ import annotations

import http.server
import socket
import struct
import threading
import time
import urllib.parse
from pathlib import Path

import cv2
import numpy as np

UNREALCV_MAGIC = 0x9E2B83C1
SERVER_LIFETIME_S = 30.0  # hard upper bound for every fake server thread
SOCKET_TIMEOUT_S = 5.0


def make_frame_bgr(height: int = 6, width: int = 8) -> np.ndarray:
    """A small BGR frame whose blue and red channels differ everywhere, to catch channel swaps."""
    frame = np.zeros((height, width, 3), dtype=np.uint8)
    frame[..., 0] = 10  # B
    frame[..., 1] = np.arange(width, dtype=np.uint8)[None, :] * 3  # G varies along x
    frame[..., 2] = 200  # R
    return frame


def free_port() -> int:
    """A loopback port with nothing listening (bound, then released)."""
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def _recv_exact(conn: socket.socket, size: int) -> bytes:
    data = b""
    while len(data) < size:
        chunk = conn.recv(size - len(data))
        if not chunk:
            raise EOFError
        data += chunk
    return data


class FakeTcpServer:
    """Accepts connections one after another and hands each to `handle(conn, index)`."""

    def __init__(self):
        self._listener = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        self._listener.bind(("127.0.0.1", 0))
        self._listener.listen(4)
        self._listener.settimeout(0.05)
        self.port = self._listener.getsockname()[1]
        self.connections = 0
        self.errors: list[BaseException] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._serve, daemon=True)

    def handle(self, conn: socket.socket, index: int) -> None:
        raise NotImplementedError

    def _serve(self) -> None:
        deadline = time.monotonic() + SERVER_LIFETIME_S
        while not self._stop.is_set() and time.monotonic() < deadline:
            try:
                conn, _ = self._listener.accept()
            except (TimeoutError, OSError):
                continue
            index, self.connections = self.connections, self.connections + 1
            conn.settimeout(SOCKET_TIMEOUT_S)
            try:
                self.handle(conn, index)
            except (EOFError, ConnectionError, TimeoutError):
                pass  # the client went away
            except Exception as err:  # surfaced by the tests through `errors`
                self.errors.append(err)
            finally:
                conn.close()

    def __enter__(self):
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        self._thread.join(timeout=SOCKET_TIMEOUT_S + 1)
        self._listener.close()


class FakeUnrealCV(FakeTcpServer):
    """Speaks UnrealCV framing; answers `vget .../lit png` with a PNG of `frame_bgr`, the rest with 'ok'.

    `drop` maps a connection index to the number of requests after which that connection is closed
    without a reply; `silent` never sends the greeting; `reject` lists commands answered with an error.
    """

    def __init__(
        self,
        frame_bgr: np.ndarray,
        drop: dict[int, int] | None = None,
        silent: bool = False,
        reject: tuple[str, ...] = (),
    ):
        super().__init__()
        ok, png = cv2.imencode(".png", frame_bgr)
        assert ok
        self.png = png.tobytes()
        self.drop = drop or {}
        self.silent = silent
        self.reject = reject
        self.commands: list[tuple[int, str]] = []

    @staticmethod
    def _send(conn: socket.socket, payload: bytes) -> None:
        conn.sendall(struct.pack("<I", UNREALCV_MAGIC) + struct.pack("<I", len(payload)) + payload)

    def handle(self, conn: socket.socket, index: int) -> None:
        if self.silent:  # never greets: holds the connection until the client gives up and closes it
            conn.recv(1)
            return
        self._send(conn, b"connected to FakeCity")
        served = 0
        while True:
            magic, size = struct.unpack("<II", _recv_exact(conn, 8))
            assert magic == UNREALCV_MAGIC, hex(magic)
            message_id, _, command = _recv_exact(conn, size).decode().partition(":")
            if index in self.drop and served >= self.drop[index]:
                return
            self.commands.append((index, command))
            served += 1
            if command in self.reject:
                body = b"error Can not set camera"
            elif command.startswith("vget") and command.endswith("/lit png"):
                body = self.png
            else:
                body = b"ok"
            self._send(conn, message_id.encode() + b":" + body)


class FakeAirSim(FakeTcpServer):
    """Speaks msgpack-RPC; records (connection, method, params); `simGetImages` returns `frame_bgr` raw."""

    def __init__(self, frame_bgr: np.ndarray, drop: dict[int, str] | None = None, fail: tuple[str, ...] = ()):
        super().__init__()
        self.frame_bgr = frame_bgr
        self.drop = drop or {}  # connection index -> method whose request closes the connection
        self.fail = fail  # methods answered with an RPC error
        self.calls: list[tuple[int, str, list]] = []

    def handle(self, conn: socket.socket, index: int) -> None:
        import msgpack

        unpacker = msgpack.Unpacker(raw=False)
        while True:
            data = conn.recv(65536)
            if not data:
                return
            unpacker.feed(data)
            for kind, msgid, method, params in unpacker:
                assert kind == 0
                if self.drop.get(index) == method:
                    return
                self.calls.append((index, method, params))
                error, result = None, None
                if method in self.fail:
                    error = f"{method}: rejected by fake server"
                elif method == "ping":
                    result = True
                elif method == "simGetImages":
                    h, w = self.frame_bgr.shape[:2]
                    result = [
                        {
                            "image_data_uint8": self.frame_bgr.tobytes(),
                            "image_data_float": [],
                            "width": w,
                            "height": h,
                            "camera_name": params[0][0]["camera_name"],
                            "message": "",
                            "pixels_as_float": False,
                            "compress": False,
                            "image_type": 0,
                        }
                    ]
                conn.sendall(msgpack.packb([1, msgid, error, result], use_bin_type=True))


class FakeSIBR:
    """The patched SIBR viewer's HTTP API: `GET /` hello, `POST /render` writes a frame into `path`."""

    def __init__(self, frame_bgr: np.ndarray, drop_posts: int = 0, status: int = 200, write: bool = True):
        self.frame_bgr = frame_bgr
        self.forms: list[dict[str, str]] = []
        self.gets = 0
        self.drop_posts = drop_posts  # the first N POSTs are closed without a reply
        self.status = status
        self.write = write
        fake = self

        class Handler(http.server.BaseHTTPRequestHandler):
            timeout = SOCKET_TIMEOUT_S

            def log_message(self, *args) -> None:
                pass

            def do_GET(self) -> None:
                fake.gets += 1
                self._reply(200, b"Hello from SIBR")

            def do_POST(self) -> None:
                length = int(self.headers["Content-Length"])
                assert self.headers["Content-Type"] == "application/x-www-form-urlencoded"
                form = dict(urllib.parse.parse_qsl(self.rfile.read(length).decode(), strict_parsing=True))
                if fake.drop_posts > 0:
                    fake.drop_posts -= 1
                    self.close_connection = True
                    return
                fake.forms.append(form)
                if fake.status != 200:
                    self._reply(fake.status, b"render failed")
                    return
                if fake.write:
                    cv2.imwrite(str(Path(form["path"]) / "20250101_000000_0.png"), fake.frame_bgr)
                self._reply(200, b"Image saved")

            def _reply(self, status: int, body: bytes) -> None:
                self.send_response(status)
                self.send_header("Content-Type", "text/plain")
                self.send_header("Content-Length", str(len(body)))
                self.end_headers()
                self.wfile.write(body)

        self._server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.port = self._server.server_address[1]
        self._thread = threading.Thread(
            target=self._server.serve_forever, kwargs={"poll_interval": 0.05}, daemon=True
        )

    def __enter__(self):
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._server.shutdown()
        self._server.server_close()
        self._thread.join(timeout=SOCKET_TIMEOUT_S)
