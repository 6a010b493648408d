"""Shared bridge bookkeeping: poses from dynamics, STOP, occupancy collisions, reconnect-once, configs."""

from __future__ import annotations

import math

import numpy as np
import pytest

from openfly_agent.sim.base import EpisodeSpec, Simulator
from openfly_agent.sim.bridges.base import BridgeConfig, BridgeError, EngineBridge, WireError, format_number
from openfly_agent.sim.occupancy import OccupancyGrid
from openfly_agent.sim.scene import SceneBounds
from openfly_agent.utils.geometry import Pose


class RecordingBridge(EngineBridge):
    """An in-memory engine: records every rendered pose; `failures` transport errors are raised first."""

    engine = "recording"
    default_port = 1234

    def __init__(self, config=None, occupancy=None, failures: int = 0):
        super().__init__(config or BridgeConfig(), occupancy)
        self.failures = failures
        self.opens = 0
        self.closes = 0
        self.rendered: list[tuple[Pose, float, str]] = []

    def _open(self) -> None:
        self.opens += 1

    def _close_transport(self) -> None:
        self.closes += 1

    def _render(self, pose: Pose, pitch_deg: float, scene_id: str) -> np.ndarray:
        if self.failures:
            self.failures -= 1
            raise ConnectionResetError("peer reset")
        self.rendered.append((pose, pitch_deg, scene_id))
        return np.zeros((2, 3, 3), dtype=np.uint8)


EPISODE = EpisodeSpec("ep", "embedded-0", Pose(0.0, 0.0, 10.0, 2 * math.pi + 0.5), pitch_deg=-45.0)


def test_bridges_satisfy_the_simulator_protocol():
    assert isinstance(RecordingBridge(), Simulator)
    assert RecordingBridge().address == ("127.0.0.1", 1234)
    assert RecordingBridge(BridgeConfig(host="10.0.0.2", port=9)).address == ("10.0.0.2", 9)


def test_poses_come_from_dynamics_and_stop_does_not_render():
    bridge = RecordingBridge()
    obs = bridge.reset(EPISODE)
    assert obs.pose.yaw == pytest.approx(0.5)  # annotation yaws are wrapped on reset
    obs, info = bridge.step(6)  # move left 3 m
    assert (obs.pose.x, obs.pose.y) == pytest.approx((-3 * math.sin(0.5), 3 * math.cos(0.5)))
    obs, _ = bridge.step(-1)  # take-off climb
    assert obs.pose.z == pytest.approx(13.0)
    _, info = bridge.step(0)
    assert info.done and len(bridge.rendered) == 3 and info.extra == {"engine": "recording"}
    assert all(pitch == -45.0 and scene == "embedded-0" for _, pitch, scene in bridge.rendered)
    with pytest.raises(ValueError, match="unknown action id 12"):
        _step_on_fresh(12)


def _step_on_fresh(action: int):
    bridge = RecordingBridge()
    bridge.reset(EPISODE)
    return bridge.step(action)


def test_occupancy_marks_colliding_moves():
    grid = OccupancyGrid.empty(SceneBounds(-20, 20, -20, 20, 0, 20), voxel_size=1.0)
    grid.mark_box(np.array([5.0, -2.0, 0.0]), np.array([6.0, 2.0, 20.0]))  # a wall across x = 5..6
    bridge = RecordingBridge(occupancy=grid)
    bridge.reset(EpisodeSpec("ep", "s", Pose(0.0, 0.0, 10.0, 0.0)))
    _, first = bridge.step(1)  # 0 -> 3 m: clear
    _, second = bridge.step(1)  # 3 -> 6 m: through the wall
    _, turn = bridge.step(2)
    assert (first.collided, second.collided, turn.collided) == (False, True, False)
    assert not second.done  # the policy (rollout/metrics) decides what a collision means


def test_reconnect_once_then_fail():
    bridge = RecordingBridge(failures=1)
    bridge.reset(EPISODE)
    assert (bridge.opens, bridge.closes) == (2, 1)
    bridge = RecordingBridge(failures=2)
    with pytest.raises(
        BridgeError,
        match=r"recording at 127\.0\.0\.1:1234: reset failed after one reconnect: "
        r"ConnectionResetError: peer reset",
    ):
        bridge.reset(EPISODE)
    assert bridge.opens == 2
    bridge = RecordingBridge(BridgeConfig(reconnect=False), failures=1)
    with pytest.raises(BridgeError, match="reconnect disabled"):
        bridge.reset(EPISODE)
    assert bridge.opens == 1
    with pytest.raises(RuntimeError, match="before reset"):
        bridge.step(1)  # a failed reset leaves no episode


def test_wire_errors_are_retried_like_transport_errors():
    class Garbled(RecordingBridge):
        def _render(self, pose, pitch_deg, scene_id):
            if self.opens == 1:
                raise WireError("bad magic")
            return super()._render(pose, pitch_deg, scene_id)

    bridge = Garbled()
    bridge.reset(EPISODE)
    assert bridge.opens == 2 and len(bridge.rendered) == 1


def test_config_and_number_format():
    with pytest.raises(ValueError, match="read_timeout_s"):
        BridgeConfig(read_timeout_s=0)
    with pytest.raises(ValueError, match="host"):
        BridgeConfig(host="")
    assert [format_number(v) for v in (-0.0, 1, 0.1 + 0.2, -1e-7)] == [
        "0.0",
        "1.0",
        "0.30000000000000004",
        "-1e-07",
    ]
