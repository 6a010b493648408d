"""UnrealCV bridge: pose conversion by hand, and a loopback fake server that checks the exact commands."""

from __future__ import annotations

import math
import struct

import numpy as np
import pytest
from bridge_fakes import FakeUnrealCV, free_port, make_frame_bgr

from openfly_agent.sim.base import EpisodeSpec
from openfly_agent.sim.bridges.base import BridgeError
from openfly_agent.sim.bridges.unrealcv import (
    UnrealCVBridge,
    UnrealCVConfig,
    pack_message,
    unrealcv_location,
    unrealcv_pose_commands,
    unrealcv_rotation,
)
from openfly_agent.utils.geometry import Pose

INIT = ["vset /cameras/spawn", "vset /camera/1/size 1920 1080"]


def _episode(pitch_deg: float = -45.0) -> EpisodeSpec:
    return EpisodeSpec(
        "env_ue_smallcity/astar_data/high_short/x",
        "env_ue_smallcity",
        Pose(1.5, -2.0, 30.0, 0.0),
        pitch_deg=pitch_deg,
    )


def test_pose_conversion_by_hand():
    pose = Pose(1.5, -2.0, 30.0, math.pi / 2)
    assert unrealcv_location(pose) == pytest.approx((150.0, 200.0, 3000.0))  # cm, y negated
    assert unrealcv_rotation(pose, -45.0) == pytest.approx((-45.0, -90.0, 0.0))  # pitch, -yaw, roll
    assert unrealcv_pose_commands(pose, -45.0) == [
        "vset /camera/0/location 150.0 200.0 3000.0",
        "vset /camera/1/location 150.0 200.0 3000.0",
        "vset /camera/0/rotation -45.0 -90.0 0.0",
        "vset /camera/1/rotation -45.0 -90.0 0.0",
    ]
    assert unrealcv_pose_commands(Pose(0.0, 0.0, 1.0, 0.0), 0.0, (1,)) == [
        "vset /camera/1/location 0.0 0.0 100.0",  # no "-0.0"
        "vset /camera/1/rotation 0.0 0.0 0.0",
    ]


def test_framing():
    assert (
        pack_message(b"0:vget /unrealcv/status")
        == struct.pack("<II", 0x9E2B83C1, 23) + b"0:vget /unrealcv/status"
    )


def test_episode_over_the_wire_and_rgb_frames():
    frame = make_frame_bgr()
    with FakeUnrealCV(frame) as server:
        bridge = UnrealCVBridge(UnrealCVConfig(port=server.port, read_timeout_s=5))
        with bridge:
            obs = bridge.reset(_episode())
            obs1, info1 = bridge.step(9)  # forward 9 m along +x
            obs2, info2 = bridge.step(2)  # turn left 30 deg
            obs3, info3 = bridge.step(0)  # STOP: no engine call
        commands = [c for _, c in server.commands]
        assert server.errors == [] and server.connections == 1
    np.testing.assert_array_equal(obs.rgb, frame[:, :, ::-1])  # PNG (BGR after decode) -> RGB
    assert obs.rgb[0, 0].tolist() == [200, 0, 10] and obs.boxes is None
    assert (obs1.pose.x, obs1.pose.y, obs1.pose.z) == pytest.approx((10.5, -2.0, 30.0))
    assert obs2.pose.yaw == pytest.approx(math.radians(30))
    assert not info1.done and info3.done and obs3.pose == obs2.pose and not info1.collided
    lit = "vget /camera/1/lit png"
    expected = (
        INIT
        + unrealcv_pose_commands(obs.pose, -45.0)
        + [lit]
        + unrealcv_pose_commands(obs1.pose, -45.0)
        + [lit]
        + unrealcv_pose_commands(obs2.pose, -45.0)
        + [lit]
    )
    assert commands == expected
    assert commands[2] == "vset /camera/0/location 150.0 200.0 3000.0"
    assert commands[4] == "vset /camera/0/rotation -45.0 0.0 0.0"
    assert commands[7] == "vset /camera/0/location 1050.0 200.0 3000.0"
    pitch, yaw, roll = (float(v) for v in commands[-2].removeprefix("vset /camera/1/rotation ").split())
    assert (pitch, yaw, roll) == pytest.approx((-45.0, -30.0, 0.0))  # a left turn is a negative UE yaw


def test_reconnects_once_after_a_dropped_connection():
    with FakeUnrealCV(make_frame_bgr(), drop={0: 3}) as server:  # first connection dies at the 4th request
        with UnrealCVBridge(UnrealCVConfig(port=server.port, read_timeout_s=5)) as bridge:
            obs = bridge.reset(_episode())
        assert server.connections == 2
        second = [c for i, c in server.commands if i == 1]
    assert (
        second[:2] == INIT and second[-1] == "vget /camera/1/lit png"
    )  # re-initialised, whole render redone
    assert obs.rgb.shape == (6, 8, 3)


def test_clear_error_after_the_one_reconnect():
    with FakeUnrealCV(make_frame_bgr(), drop={0: 2, 1: 2}) as server:
        bridge = UnrealCVBridge(UnrealCVConfig(port=server.port, read_timeout_s=5))
        with pytest.raises(
            BridgeError, match=r"unrealcv at 127\.0\.0\.1:\d+: reset failed after one reconnect"
        ):
            bridge.reset(_episode())
        assert server.connections == 2


def test_no_server_and_silent_server_fail_clearly():
    with pytest.raises(BridgeError, match="Is the engine running"):
        UnrealCVBridge(UnrealCVConfig(port=free_port(), connect_timeout_s=1)).reset(_episode())
    with FakeUnrealCV(make_frame_bgr(), silent=True) as server:
        bridge = UnrealCVBridge(UnrealCVConfig(port=server.port, connect_timeout_s=0.2, reconnect=False))
        with pytest.raises(BridgeError, match="reconnect disabled.*timed out"):
            bridge.reset(_episode())


def test_engine_error_reply_is_not_retried():
    command = "vset /camera/0/rotation -45.0 0.0 0.0"
    with FakeUnrealCV(make_frame_bgr(), reject=(command,)) as server:
        bridge = UnrealCVBridge(UnrealCVConfig(port=server.port, read_timeout_s=5))
        with bridge, pytest.raises(BridgeError, match="rejected 'vset /camera/0/rotation"):
            bridge.reset(_episode())
        assert server.connections == 1


def test_step_before_reset_and_after_stop():
    bridge = UnrealCVBridge(UnrealCVConfig(port=free_port()))
    with pytest.raises(RuntimeError, match="before reset"):
        bridge.step(1)
    with FakeUnrealCV(make_frame_bgr()) as server:
        with UnrealCVBridge(
            UnrealCVConfig(port=server.port, read_timeout_s=5, width=0, height=0, spawn_camera=False)
        ) as bridge:
            bridge.reset(_episode(pitch_deg=0.0))
            bridge.step(0)
            with pytest.raises(RuntimeError, match="is over"):
                bridge.step(1)
        assert [c for _, c in server.commands][0] == "vset /camera/0/location 150.0 200.0 3000.0"


def test_config_validation():
    with pytest.raises(ValueError, match="port"):
        UnrealCVConfig(port=70000)
    with pytest.raises(ValueError, match="width/height"):
        UnrealCVConfig(width=640, height=0)
