"""Baselines on the real released episodes of eval_test.json: the published trivial-baseline numbers."""

from __future__ import annotations

import pytest
from eval_helpers import PoseSimulator

from openfly_agent import constants as C
from openfly_agent.data.config import ReaderOptions
from openfly_agent.data.openfly_reader import read_annotation_file
from openfly_agent.eval.baselines import ConstantPolicy, OraclePolicy
from openfly_agent.eval.report import policy_results
from openfly_agent.eval.rollout import teleport_record
from openfly_agent.rollout.runner import LockstepRunner
from openfly_agent.sim.vector import VectorSimulator

# docs/OFFICIAL_OPENFLY.md 6.2: STOP at step 0 succeeds on 26 of 240 (per-scene SR in percent).
STOP_AT_START_SR = {
    "env_airsim_16": 10.0, "env_airsim_18": 13.3, "env_airsim_23": 6.7, "env_airsim_26": 3.3,
    "env_airsim_sh": 0.0, "env_airsim_gz": 10.0, "env_ue_smallcity": 16.7, "env_ue_bigcity": 26.7,
}  # fmt: skip


@pytest.fixture(scope="module")
def released(openfly_fixtures):
    options = ReaderOptions(takeoff_landing="keep")
    return read_annotation_file(openfly_fixtures / "eval_test.json", options, split=C.SPLIT_TEST_SEEN)


def test_stop_at_start_reproduces_the_published_rates(released):
    records = []
    runner = LockstepRunner(
        ConstantPolicy("stop", C.ACTION_STOP), VectorSimulator(sims=[PoseSimulator()] * 8)
    )
    runner.show_progress = False
    runner.run(released, C.SPLIT_TEST_SEEN, records.append)
    assert len(records) == 240
    table = policy_results("stop", records, ["openfly", "standard"])["splits"][C.SPLIT_TEST_SEEN]
    for profile in ("openfly", "standard"):
        assert table[profile]["overall"]["sr_pct"] == pytest.approx(100 * 26 / 240)
        per_scene = {s: round(v["sr_pct"], 1) for s, v in table[profile]["per_scene"].items()}
        assert per_scene == STOP_AT_START_SR
    # OSR equals SR for an agent that stops at once (OpenFly#93 reports exactly that).
    assert table["openfly"]["overall"]["osr_pct"] == table["openfly"]["overall"]["sr_pct"]


def test_oracle_teleports_along_released_poses(released):
    oracle = OraclePolicy(released, mode="auto")
    replayable = [e for e in released if oracle.replays(e.episode_id)]
    assert len(replayable) < len(
        released
    )  # the label / pose quirks of the release (docs/OFFICIAL_OPENFLY.md 1.2)
    records = [teleport_record(e, C.SPLIT_TEST_SEEN, "oracle", C.MAX_EPISODE_STEPS) for e in released]
    assert max(len(e) for e in released) <= C.MAX_EPISODE_STEPS  # 62 at most: nothing is cut
    table = policy_results("oracle", records, ["openfly", "standard"])["splits"][C.SPLIT_TEST_SEEN]
    for profile in ("openfly", "standard"):
        assert table[profile]["overall"]["sr_pct"] == 100.0
        assert table[profile]["overall"]["ne_m"] == pytest.approx(0.0, abs=1e-9)
