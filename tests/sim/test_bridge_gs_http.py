"""3DGS SIBR bridge: world-to-camera pose by hand and by property, and the HTTP round trip on loopback."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from bridge_fakes import FakeSIBR, free_port, make_frame_bgr
from hypothesis import given, settings
from hypothesis import strategies as st

from openfly_agent.sim.base import EpisodeSpec
from openfly_agent.sim.bridges.base import BridgeError
from openfly_agent.sim.bridges.gs_http import (
    OFFICIAL_CAMERA_LINE,
    GSHttpBridge,
    GSHttpConfig,
    quaternion_from_matrix,
    sibr_image_line,
    sibr_world_to_camera,
)
from openfly_agent.utils.geometry import Pose

R2 = math.sqrt(0.5)


def _matrix(q) -> np.ndarray:
    """Textbook unit quaternion (w, x, y, z) -> rotation matrix."""
    w, x, y, z = q
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def test_world_to_camera_by_hand():
    q, t = sibr_world_to_camera(Pose(5.15, 10.3, 15.45, 0.0), pitch_deg=0.0, scale_ratio=5.15)
    # R = [[0,-1,0],[0,0,-1],[1,0,0]] (body FLU -> camera RDF); p = (1, 2, 3); T = -R p = (2, 3, -1)
    np.testing.assert_allclose(q, [0.5, 0.5, -0.5, 0.5], atol=1e-12)
    np.testing.assert_allclose(t, [2.0, 3.0, -1.0], atol=1e-12)
    q, t = sibr_world_to_camera(Pose(5.15, 10.3, 15.45, math.pi / 2), pitch_deg=0.0, scale_ratio=5.15)
    # R = B Rz(-90 deg) = Rx(+90 deg) = [[1,0,0],[0,0,-1],[0,1,0]]; T = -(1, -3, 2)
    np.testing.assert_allclose(q, [R2, R2, 0.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(t, [-1.0, 3.0, -2.0], atol=1e-12)
    assert sibr_image_line(np.array([1.0, 0, 0, 0]), np.array([2.0, -0.0, 0.5])) == (
        "0 1.0 0.0 0.0 0.0 2.0 0.0 0.5 0 00000000.png"
    )


@settings(max_examples=60, deadline=None)
@given(st.floats(-math.pi, math.pi), st.floats(-89.0, 89.0), st.floats(-500, 500), st.floats(0.5, 10.0))
def test_camera_looks_along_the_heading_and_sits_at_the_scaled_position(yaw, pitch_deg, x, scale):
    pose = Pose(x, 2.0 * x, 60.0, yaw)
    q, t = sibr_world_to_camera(pose, pitch_deg, scale)
    assert q[0] >= 0 and np.linalg.norm(q) == pytest.approx(1.0)
    rotation = _matrix(q)  # world -> camera
    p = math.radians(pitch_deg)
    forward = [math.cos(p) * math.cos(yaw), math.cos(p) * math.sin(yaw), math.sin(p)]
    np.testing.assert_allclose(
        rotation[2], forward, atol=1e-9
    )  # camera +z: heading, pitched (negative = down)
    np.testing.assert_allclose(
        rotation[0], [math.sin(yaw), -math.cos(yaw), 0.0], atol=1e-9
    )  # camera +x: right
    np.testing.assert_allclose(-rotation.T @ t, pose.position / scale, atol=1e-9)  # camera centre


@settings(max_examples=60, deadline=None)
@given(st.lists(st.floats(-1, 1), min_size=4, max_size=4).filter(lambda v: np.linalg.norm(v) > 0.1))
def test_quaternion_from_matrix_round_trip(values):
    q = np.array(values) / np.linalg.norm(values)
    q = -q if q[0] < 0 else q
    np.testing.assert_allclose(_matrix(quaternion_from_matrix(_matrix(q))), _matrix(q), atol=1e-9)


def _episode(scene: str = "env_gs_nwpu02", pitch_deg: float = 0.0) -> EpisodeSpec:
    return EpisodeSpec(
        f"{scene}/astar_data/high_long/x", scene, Pose(5.15, 10.3, 15.45, 0.0), pitch_deg=pitch_deg
    )


def _numbers(image_line: str) -> tuple[np.ndarray, np.ndarray]:
    fields = image_line.split()
    assert fields[0] == "0" and fields[8] == "0" and fields[9] == "00000000.png" and len(fields) == 10
    values = np.array([float(v) for v in fields[1:8]])
    return values[:4], values[4:]


def test_render_round_trip_reads_the_written_frame(tmp_path):
    frame = make_frame_bgr()
    config = GSHttpConfig(
        port=free_port(), output_dir=str(tmp_path), pitch_override_deg=None, read_timeout_s=5
    )
    with FakeSIBR(frame) as server:
        config.port = server.port
        with GSHttpBridge(config) as bridge:
            obs = bridge.reset(_episode())
            obs1, _ = bridge.step(1)  # forward 3 m
        assert server.gets == 1 and len(server.forms) == 2
    np.testing.assert_array_equal(obs.rgb, frame[:, :, ::-1])  # BGR file -> RGB
    first = server.forms[0]
    assert first["camera"] == OFFICIAL_CAMERA_LINE
    q, t = _numbers(first["image"])
    np.testing.assert_allclose(q, [0.5, 0.5, -0.5, 0.5], atol=1e-9)
    np.testing.assert_allclose(t, [2.0, 3.0, -1.0], atol=1e-9)
    assert Path(first["path"]).parent == tmp_path and first["path"].endswith("/")
    _, t1 = _numbers(server.forms[1]["image"])
    np.testing.assert_allclose(t1, [2.0, 3.0, -(5.15 + 3.0) / 5.15], atol=1e-9)  # x grew by 3 m / scale
    assert obs1.pose.x == pytest.approx(8.15)
    assert list(tmp_path.iterdir()) == []  # frames are deleted once read


def test_scale_and_pitch_choices(tmp_path):
    with FakeSIBR(make_frame_bgr()) as server:
        bridge = GSHttpBridge(GSHttpConfig(port=server.port, output_dir=str(tmp_path), keep_frames=True))
        with bridge:
            bridge.reset(_episode("env_gs_sjtu02", pitch_deg=-45.0))
            with pytest.raises(BridgeError, match="no scale ratio for 3DGS scene 'env_gs_other'"):
                bridge.reset(_episode("env_gs_other"))
    q, t = _numbers(server.forms[0]["image"])
    q_expected, t_expected = sibr_world_to_camera(_episode().start, -40.0, 4.75)  # official pitch, sjtu02
    np.testing.assert_allclose(q, q_expected, atol=1e-9)
    np.testing.assert_allclose(t, t_expected, atol=1e-9)
    assert len(list(tmp_path.glob("*/*.png"))) == 1  # keep_frames


def _reset_against(server: FakeSIBR, output_dir: Path):
    with GSHttpBridge(GSHttpConfig(port=server.port, output_dir=str(output_dir), read_timeout_s=5)) as bridge:
        return bridge.reset(_episode())


def test_http_failures_are_clear(tmp_path):
    with FakeSIBR(make_frame_bgr(), drop_posts=1) as server:
        assert _reset_against(server, tmp_path).rgb.shape == (6, 8, 3)  # dropped once, reconnected, retried
        assert server.gets == 2 and len(server.forms) == 1
    cases = [
        ({"drop_posts": 2}, r"gs_http at 127\.0\.0\.1:\d+: reset failed after one reconnect"),
        ({"status": 500}, "answered 500"),
        ({"write": False}, "wrote no image"),
    ]
    for options, message in cases:
        with FakeSIBR(make_frame_bgr(), **options) as server, pytest.raises(BridgeError, match=message):
            _reset_against(server, tmp_path)
    with pytest.raises(BridgeError, match="Is the engine running"):
        GSHttpBridge(GSHttpConfig(port=free_port(), connect_timeout_s=1)).reset(_episode())


def test_temporary_output_dir_is_removed_on_close():
    with FakeSIBR(make_frame_bgr()) as server:
        bridge = GSHttpBridge(GSHttpConfig(port=server.port))
        bridge.reset(_episode())
        output_dir = bridge._output_dir
        assert output_dir is not None and output_dir.is_dir()
        bridge.close()
    assert not output_dir.exists()
