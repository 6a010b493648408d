"""Evaluation through an engine bridge: the runner against a fake UnrealCV server on loopback."""

from __future__ import annotations

import numpy as np
from bridge_fakes import FakeUnrealCV, make_frame_bgr
from eval_helpers import make_episode

from openfly_agent import constants as C
from openfly_agent.eval.baselines import OraclePolicy
from openfly_agent.eval.config import BridgeSimSettings, EvalConfig, SimSettings, UnrealCVSimSettings
from openfly_agent.eval.distributed import ProcessInfo
from openfly_agent.eval.factory import make_bridge_env, scene_occupancy
from openfly_agent.eval.report import policy_results
from openfly_agent.rollout.runner import LockstepRunner
from openfly_agent.sim.bridges.airsim import AirSimBridge
from openfly_agent.sim.bridges.gs_http import GSHttpBridge
from openfly_agent.sim.bridges.unrealcv import UnrealCVBridge
from openfly_agent.sim.pointcloud import write_pcd


def _episodes():
    return [
        make_episode("env_ue_smallcity/astar_data/low_short/a", [9, 9, 2, 1, 0], scene_id="env_ue_smallcity"),
        make_episode("env_ue_smallcity/astar_data/low_short/b", [1, 1, 0], start=(5.0, -2.0, 20.0, 1.0),
                     scene_id="env_ue_smallcity"),
    ]  # fmt: skip


def test_oracle_over_unrealcv_reaches_every_goal(tmp_path):
    episodes = _episodes()
    # A wall of points at x = 20..22 across the first route: its second 9 m move (9 -> 18) stays short of
    # it, the 3 m move after the turn (to x = 20.6) enters it.
    wall = np.array(
        [[x, y, z] for x in (20.5, 21.5) for y in np.arange(-10, 10, 0.5) for z in np.arange(0, 60, 0.5)]
    )
    write_pcd(tmp_path / "env_ue_smallcity.pcd", wall, binary=True)
    with FakeUnrealCV(make_frame_bgr()) as server:
        cfg = EvalConfig(policy="oracle", progress=False, sim=UnrealCVSimSettings())
        cfg.sim.unrealcv.port = server.port
        cfg.sim.unrealcv.read_timeout_s = 5.0
        cfg.sim.occupancy_pcd = str(tmp_path / "{scene_id}.pcd")
        env = make_bridge_env(cfg.sim, ProcessInfo())
        records = []
        LockstepRunner(OraclePolicy(episodes), env, show_progress=False).run(
            episodes, C.SPLIT_TEST_SEEN, records.append
        )
        env.close()
        locations = [c for _, c in server.commands if c.startswith("vset /camera/0/location")]
        assert server.errors == []
    a, b = sorted(records, key=lambda r: r.episode_id)
    assert a.actions == [9, 9, 2, 1, 0] and a.stopped and a.collision_steps == [3]
    # Start, 4 moves for a and start, 2 moves for b; UnrealCV gets centimetres with y negated.
    assert len(locations) == 5 + 3
    x, y, z = (float(v) for v in locations[5].split()[-3:])
    assert (x, y, z) == (500.0, 200.0, 2000.0)
    table = policy_results("oracle", records, ["openfly", "standard"])["splits"][C.SPLIT_TEST_SEEN]
    assert table["openfly"]["overall"]["sr_pct"] == 100.0  # collisions ignored
    assert table["standard"]["overall"]["sr_pct"] == 50.0  # the wall fails route a
    grid = scene_occupancy(str(tmp_path / "{scene_id}.pcd"), "env_ue_smallcity", 1.0)
    assert grid.is_occupied(np.array([[21.0, 0.0, 30.0], [10.0, 0.0, 30.0]])).tolist() == [True, False]


def test_each_bridge_variant_names_its_bridge():
    variants = {name: SimSettings.get_choice_class(name) for name in SimSettings.get_known_choices()}
    bridges = {name: cls.bridge_class for name, cls in variants.items() if issubclass(cls, BridgeSimSettings)}
    assert bridges == {"unrealcv": UnrealCVBridge, "airsim": AirSimBridge, "gs_http": GSHttpBridge}
