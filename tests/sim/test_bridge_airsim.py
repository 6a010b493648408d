"""AirSim bridge: NED pose conversion by hand, msgpack-RPC against a loopback fake, frame decoding."""

from __future__ import annotations

import math
import sys

import numpy as np
import pytest
from bridge_fakes import FakeAirSim, free_port, make_frame_bgr

from openfly_agent.sim.base import EpisodeSpec
from openfly_agent.sim.bridges.airsim import (
    AirSimBridge,
    AirSimConfig,
    airsim_pose,
    decode_image_response,
    to_quaternion,
)
from openfly_agent.sim.bridges.base import BridgeError
from openfly_agent.utils.geometry import Pose
from openfly_agent.utils.processes import run_group

R2 = math.sqrt(0.5)


def _episode(pitch_deg: float = 0.0) -> EpisodeSpec:
    return EpisodeSpec(
        "env_airsim_16/astar_data/low_short/x",
        "env_airsim_16",
        Pose(10.0, 20.0, 30.0, math.pi / 2),
        pitch_deg=pitch_deg,
    )


def test_quaternion_and_ned_pose_by_hand():
    assert to_quaternion(0.0, 0.0, 0.0) == pytest.approx((1.0, 0.0, 0.0, 0.0))
    assert to_quaternion(0.0, 0.0, -math.pi / 2) == pytest.approx((R2, 0.0, 0.0, -R2))  # (w, x, y, z)
    c, s = math.cos(math.pi / 8), math.sin(math.pi / 8)
    assert to_quaternion(-math.pi / 4, 0.0, 0.0) == pytest.approx((c, 0.0, -s, 0.0))  # pitch about y
    pose = airsim_pose(Pose(10.0, 20.0, 30.0, math.pi / 2), 0.0)
    assert pose["position"] == pytest.approx({"x_val": 10.0, "y_val": -20.0, "z_val": -30.0})  # NED
    assert pose["orientation"] == pytest.approx({"w_val": R2, "x_val": 0.0, "y_val": 0.0, "z_val": -R2})


def test_decode_bgr_bgra_and_empty_frames():
    frame = make_frame_bgr()
    h, w = frame.shape[:2]
    rgb = decode_image_response({"image_data_uint8": frame.tobytes(), "width": w, "height": h}, "cam")
    np.testing.assert_array_equal(rgb, frame[:, :, ::-1])
    bgra = np.concatenate([frame, np.full((h, w, 1), 255, np.uint8)], axis=2)
    rgb4 = decode_image_response({"image_data_uint8": list(bgra.tobytes()), "width": w, "height": h}, "cam")
    np.testing.assert_array_equal(rgb4, frame[:, :, ::-1])
    with pytest.raises(BridgeError, match="empty image for camera 'front_custom'"):
        decode_image_response({"image_data_uint8": b"", "width": 0, "height": 0}, "front_custom")
    with pytest.raises(BridgeError, match="does not fit"):
        decode_image_response({"image_data_uint8": b"\x00" * 7, "width": 2, "height": 1}, "cam")


def test_episode_over_msgpack_rpc():
    frame = make_frame_bgr()
    with FakeAirSim(frame) as server:
        with AirSimBridge(AirSimConfig(port=server.port, read_timeout_s=5)) as bridge:
            obs = bridge.reset(_episode(pitch_deg=-45.0))
            obs1, _ = bridge.step(4)  # ascend 3 m
            _, info = bridge.step(0)
        calls = [(m, p) for _, m, p in server.calls]
        assert server.errors == [] and server.connections == 1
    np.testing.assert_array_equal(obs.rgb, frame[:, :, ::-1])
    assert obs1.pose.z == pytest.approx(33.0) and info.done
    methods = [m for m, _ in calls]
    assert (
        methods
        == ["ping", "enableApiControl", "armDisarm"]
        + ["moveByVelocityBodyFrame", "simSetVehiclePose", "simGetImages"] * 2
    )
    assert calls[1][1] == [True, ""] and calls[2][1] == [True, ""]
    assert calls[3][1] == [0.0, 0.0, 0.0, 0.02, 0, {"is_rate": True, "yaw_or_rate": 0.0}, ""]
    pose_map, ignore_collision, vehicle = calls[4][1]
    assert ignore_collision is True and vehicle == ""
    assert pose_map["position"] == pytest.approx({"x_val": 10.0, "y_val": -20.0, "z_val": -30.0})
    # quaternion(pitch -45 deg, roll 0, yaw -90 deg): w, x, y, z by the AirSim formula
    c, s = math.cos(math.pi / 8), math.sin(math.pi / 8)
    assert pose_map["orientation"] == pytest.approx(
        {"w_val": R2 * c, "x_val": -R2 * s, "y_val": -R2 * s, "z_val": -R2 * c}
    )
    assert calls[7][1][0]["position"]["z_val"] == pytest.approx(-33.0)
    assert calls[5][1] == [
        [{"camera_name": "front_custom", "image_type": 0, "pixels_as_float": False, "compress": False}],
        "",
        False,
    ]


def test_reconnect_once_then_clear_error():
    with FakeAirSim(make_frame_bgr(), drop={0: "simGetImages"}) as server:
        with AirSimBridge(
            AirSimConfig(port=server.port, read_timeout_s=5, hover_before_pose=False)
        ) as bridge:
            bridge.reset(_episode())
        assert server.connections == 2
        assert [m for i, m, _ in server.calls if i == 1] == [
            "ping",
            "enableApiControl",
            "armDisarm",
            "simSetVehiclePose",
            "simGetImages",
        ]
    with FakeAirSim(make_frame_bgr(), drop={0: "ping", 1: "ping"}) as server:
        with pytest.raises(
            BridgeError, match=r"airsim at 127\.0\.0\.1:\d+: reset failed after one reconnect"
        ):
            AirSimBridge(AirSimConfig(port=server.port, read_timeout_s=5)).reset(_episode())
        assert server.connections == 2
    with pytest.raises(BridgeError, match="Is the engine running"):
        AirSimBridge(AirSimConfig(port=free_port(), connect_timeout_s=1)).reset(_episode())


def test_rpc_error_is_reported_without_reconnect():
    expected = "AirSim simSetVehiclePose failed: .*rejected by fake server"
    with FakeAirSim(make_frame_bgr(), fail=("simSetVehiclePose",)) as server:
        bridge = AirSimBridge(AirSimConfig(port=server.port, read_timeout_s=5))
        with bridge, pytest.raises(BridgeError, match=expected):
            bridge.reset(_episode())
        assert server.connections == 1


def test_msgpack_is_imported_lazily_and_named_when_missing(monkeypatch):
    code = "import sys, openfly_agent.sim.bridges.airsim; print('msgpack' in sys.modules)"
    out = run_group([sys.executable, "-c", code], timeout=120)
    assert out.returncode == 0 and out.stdout.strip() == "False", out.stderr
    monkeypatch.setitem(sys.modules, "msgpack", None)  # makes `import msgpack` fail
    with pytest.raises(ImportError, match=r"openfly-agent\[bridges\]"):
        AirSimBridge(AirSimConfig(port=free_port())).reset(_episode())
