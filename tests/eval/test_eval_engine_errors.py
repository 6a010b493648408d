"""eval.py against engines that fail: unreachable before the first episode, or failing mid-run.

An engine that cannot be reached ends the run at once (exit 2, one line naming engine, host and port, nothing
written). An episode the engine fails is recorded as an error, left out of every metric, counted in the tables,
makes eval.py exit 1, and is tried again by the same command.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from bridge_fakes import FakeUnrealCV, free_port, make_frame_bgr
from data_factories import make_episode, make_frames
from eval_helpers import eval_main

from openfly_agent import constants as C
from openfly_agent.data.openfly_reader import load_openfly_dataset
from openfly_agent.data.writer import OpenFlyDatasetWriter
from openfly_agent.eval.distributed import read_all_logs
from openfly_agent.eval.report import policy_results
from openfly_agent.rollout.episodes import start_pose
from openfly_agent.sim.bridges.unrealcv import unrealcv_pose_commands

EPISODE_IDS = [f"env_ue_smallcity/astar_data/low_short/ep{i}" for i in range(3)]


@pytest.fixture(scope="module")
def dataset(tmp_path_factory) -> Path:
    """Three test-seen episodes of a real-engine scene (frames are the engine's, the files only need some)."""
    root = tmp_path_factory.mktemp("engine-data")
    writer = OpenFlyDatasetWriter(root)
    for seed, episode_id in enumerate(EPISODE_IDS):
        episode = make_episode(episode_id, [1, 2, 1, 0], split=C.SPLIT_TEST_SEEN, seed=seed)
        writer.write_episode(episode, make_frames(len(episode), seed=seed))
    writer.finalize()
    return root


def _args(dataset: Path, out: Path, engine: str, port: int) -> list[str]:
    return [
        "--policy", "oracle", f"--split=[{C.SPLIT_TEST_SEEN}]", f"--sim.type={engine}", f"--sim.{engine}.port={port}",
        f"--sim.{engine}.connect_timeout_s=2", f"--sim.{engine}.read_timeout_s=5", "--plots=0",
        "--progress=false", f"--dataset_root={dataset}", f"--output_dir={out}",
    ]  # fmt: skip


@pytest.mark.parametrize("engine", ["unrealcv", "airsim", "gs_http"])
def test_an_unreachable_engine_fails_the_run_before_any_episode(engine, dataset, tmp_path, capsys):
    port = free_port()  # nothing listens there
    code = eval_main()(_args(dataset, tmp_path / "out", engine, port))
    err = [line for line in capsys.readouterr().err.splitlines() if line.startswith("eval.py:")]
    assert code == 2
    assert len(err) == 1 and engine in err[0] and f"127.0.0.1:{port}" in err[0], err
    assert not (tmp_path / "out").exists()  # no results, no log: nothing that could pass for a run


def test_an_engine_error_mid_run_is_counted_not_scored_and_retried(dataset, tmp_path, capsys):
    episodes = load_openfly_dataset(dataset, C.SPLIT_TEST_SEEN)
    broken = episodes[1]
    # The engine refuses to move the camera to the second episode's start: its reset fails.
    refused = unrealcv_pose_commands(start_pose(broken), broken.pitch_deg, (0, 1))[0]
    out = tmp_path / "out"
    with FakeUnrealCV(make_frame_bgr(), reject=(refused,)) as server:
        code = eval_main()(_args(dataset, out, "unrealcv", server.port))
    assert code == 1
    assert "ended in an engine error" in capsys.readouterr().err
    records = {r.episode_id: r for r in read_all_logs(out / "oracle")}
    assert records[broken.episode_id].end_reason == "error" and "rejected" in records[broken.episode_id].error
    results = json.loads((out / "oracle" / C.RESULTS_JSON).read_text())
    overall = results["splits"][C.SPLIT_TEST_SEEN]["openfly"]["overall"]
    assert results["errors"] == {C.SPLIT_TEST_SEEN: 1}
    assert overall["episodes"] == 2 and overall["errors"] == 1 and overall["sr_pct"] == 100.0  # not scored
    assert "| Errors |" in (out / "oracle" / C.RESULTS_MD).read_text()
    assert "| Errors |" in (out / "summary.md").read_text()

    # The same command with a healthy engine retries the failed episode only, and the run is clean.
    with FakeUnrealCV(make_frame_bgr()) as server:
        code = eval_main()(_args(dataset, out, "unrealcv", server.port))
        moved = [c for _, c in server.commands if c.startswith("vset /camera/0/location")]
    assert code == 0
    assert moved[0] == refused and len(moved) == 1 + 3  # start + 3 moves of the retried episode
    records = read_all_logs(out / "oracle")
    assert len(records) == 3 and not any(r.errored for r in records)
    assert len((out / "oracle" / C.EPISODES_JSONL).read_text().splitlines()) == 3  # the error record is gone
    results = json.loads((out / "oracle" / C.RESULTS_JSON).read_text())
    assert results["errors"] == {C.SPLIT_TEST_SEEN: 0}
    assert results["splits"] == policy_results("oracle", records, ["openfly", "standard"])["splits"]
